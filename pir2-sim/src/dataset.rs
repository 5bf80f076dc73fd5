//! Demonstrations: collection into in-memory [`Episode`]s, and LeRobotDataset v3.0
//! (state-only) writing and reading. Shared by every task of the crate.
//!
//! # In memory
//!
//! [`collect`] runs an [`Expert`] on an [`Environment`] and hands each finished [`Episode`]
//! (fast and slow observations, clean expert actions, row-major `f32`) to a sink; the
//! trainer can use [`collect_episodes`] and never touch parquet. Actions are *executed*
//! with Gaussian noise ([`CollectConfig::action_noise`]) while the *labels* are the clean
//! expert actions. The slow channel is stored undelayed; the trainer applies `d_vis`.
//!
//! # On disk (LeRobotDataset v3.0, no videos)
//!
//! ```text
//! root/
//!   data/chunk-000/file-000.parquet          one row per frame, many episodes per file
//!   meta/info.json                           codebase_version "v3.0", fps, features, totals, path templates
//!   meta/stats.json                          per feature: min, max, mean, std, count, q01, q10, q50, q90, q99
//!   meta/tasks.parquet                       task_index, task (pandas index "task")
//!   meta/episodes/chunk-000/file-000.parquet one row per episode: episode_index, tasks, length,
//!                                            data/chunk_index, data/file_index, dataset_from_index,
//!                                            dataset_to_index, meta/episodes/chunk_index,
//!                                            meta/episodes/file_index, stats/<feature>/<stat>, pir2/*
//! ```
//!
//! Frame columns: `observation.state` (fast, fixed-size list of `f32`),
//! `observation.environment_state` (slow), `action`, `timestamp` (`f32`, s), `frame_index`,
//! `episode_index`, `index` (global frame index), `task_index` (`i64`), `next.done`,
//! `next.success` (`bool`, true on the last frame of an episode that ended / succeeded).
//!
//! Writing never replaces an existing dataset silently: [`WriteMode::New`] refuses a
//! non-empty directory, [`WriteMode::Resume`] appends episodes in new data/episode files
//! (one pair per writing session), [`WriteMode::Overwrite`] deletes `data/` and `meta/`
//! first. Files are written under a temporary name and renamed; `meta/info.json` is written
//! last, so an interrupted session leaves the previous dataset readable.

use std::collections::BTreeMap;
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow_array::builder::{ListBuilder, StringBuilder};
use arrow_array::cast::AsArray;
use arrow_array::types::{Float32Type, Float64Type, Int32Type, Int64Type, UInt64Type};
use arrow_array::{
    Array, ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, Int64Array, ListArray,
    RecordBatch, StringArray, UInt64Array,
};
use arrow_schema::{DataType, Field, Schema};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;
use pir2_runtime::Environment;
use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::error::{Error, Result};
use crate::expert::Expert;

/// Codebase version written to `meta/info.json`.
pub const CODEBASE_VERSION: &str = "v3.0";
/// Max files per chunk directory (LeRobot's `DEFAULT_CHUNK_SIZE`).
pub const CHUNKS_SIZE: usize = 1000;
/// Data path template (LeRobot's `DEFAULT_DATA_PATH`).
pub const DATA_PATH: &str = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
/// Episodes metadata path template (LeRobot's `DEFAULT_EPISODES_PATH`).
pub const EPISODES_PATH: &str =
    "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
/// `meta/info.json`.
pub const INFO_PATH: &str = "meta/info.json";
/// `meta/stats.json`.
pub const STATS_PATH: &str = "meta/stats.json";
/// `meta/tasks.parquet`.
pub const TASKS_PATH: &str = "meta/tasks.parquet";
/// Feature key of the fast (proprioceptive) observation.
pub const KEY_FAST: &str = "observation.state";
/// Feature key of the slow (camera) observation.
pub const KEY_SLOW: &str = "observation.environment_state";
/// Feature key of the action.
pub const KEY_ACTION: &str = "action";
/// Quantiles written to `stats.json` (LeRobot's `DEFAULT_QUANTILES`).
pub const QUANTILES: [(f64, &str); 5] = [
    (0.01, "q01"),
    (0.10, "q10"),
    (0.50, "q50"),
    (0.90, "q90"),
    (0.99, "q99"),
];

// ------------------------------------------------------------------------------------
// In-memory episodes
// ------------------------------------------------------------------------------------

/// One demonstration in memory: per frame a fast observation, a slow observation and the
/// (clean) action label, stored row-major.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Episode {
    /// Fast observations, `len × fast_dim`.
    pub fast: Vec<f32>,
    /// Slow observations (undelayed), `len × slow_dim`.
    pub slow: Vec<f32>,
    /// Action labels, `len × action_dim`.
    pub action: Vec<f32>,
    /// Width of one fast observation.
    pub fast_dim: usize,
    /// Width of one slow observation (0 if the dataset has none).
    pub slow_dim: usize,
    /// Width of one action.
    pub action_dim: usize,
    /// Whether the episode ended (by success, failure or time-out) on its last frame.
    pub done: bool,
    /// Whether the episode ended in success.
    pub success: bool,
    /// Environment seed of the episode (0 if unknown).
    pub seed: u64,
    /// Task index (into the dataset's task list).
    pub task_index: i64,
}

impl Episode {
    /// An empty episode with the given widths.
    pub fn new(fast_dim: usize, slow_dim: usize, action_dim: usize) -> Self {
        Self {
            fast_dim,
            slow_dim,
            action_dim,
            ..Default::default()
        }
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.action.len().checked_div(self.action_dim).unwrap_or(0)
    }

    /// No frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Append one frame (slices must have the episode's widths).
    pub fn push(&mut self, fast: &[f32], slow: &[f32], action: &[f32]) {
        assert_eq!(fast.len(), self.fast_dim, "fast width");
        assert_eq!(slow.len(), self.slow_dim, "slow width");
        assert_eq!(action.len(), self.action_dim, "action width");
        self.fast.extend_from_slice(fast);
        self.slow.extend_from_slice(slow);
        self.action.extend_from_slice(action);
    }

    /// Fast observation of frame `t`.
    pub fn fast(&self, t: usize) -> &[f32] {
        &self.fast[t * self.fast_dim..(t + 1) * self.fast_dim]
    }

    /// Slow observation of frame `t`.
    pub fn slow(&self, t: usize) -> &[f32] {
        &self.slow[t * self.slow_dim..(t + 1) * self.slow_dim]
    }

    /// Action label of frame `t`.
    pub fn action(&self, t: usize) -> &[f32] {
        &self.action[t * self.action_dim..(t + 1) * self.action_dim]
    }

    fn check(&self, index: usize, spec: &DatasetSpec) -> Result<()> {
        let bad = |reason: String| {
            Err(Error::EpisodeShape {
                episode: index,
                reason,
            })
        };
        let n = self.len();
        if n == 0 {
            return bad("no frames".into());
        }
        for (what, dim, want, data) in [
            ("fast", self.fast_dim, spec.fast_names.len(), &self.fast),
            ("slow", self.slow_dim, spec.slow_names.len(), &self.slow),
            (
                "action",
                self.action_dim,
                spec.action_names.len(),
                &self.action,
            ),
        ] {
            if dim != want {
                return bad(format!("{what} width {dim}, dataset has {want}"));
            }
            if data.len() != n * dim {
                return bad(format!(
                    "{what} holds {} values, expected {n} × {dim}",
                    data.len()
                ));
            }
        }
        if self.task_index < 0 || self.task_index as usize >= spec.tasks.len() {
            return bad(format!(
                "task_index {} outside the {} tasks",
                self.task_index,
                spec.tasks.len()
            ));
        }
        Ok(())
    }
}

// ------------------------------------------------------------------------------------
// Collection
// ------------------------------------------------------------------------------------

/// How demonstrations are collected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CollectConfig {
    /// Number of episodes to keep.
    pub episodes: usize,
    /// σ of the Gaussian noise added to the *executed* action (labels stay clean).
    pub action_noise: f64,
    /// Base seed; attempt `j` runs the environment with seed `episode_seed(seed, j)`.
    pub seed: u64,
    /// Keep only successful episodes (failed attempts are run and dropped).
    pub only_success: bool,
    /// Give up after this many attempts per kept episode (guards against an expert that
    /// never succeeds).
    pub max_attempts_per_episode: usize,
    /// Task index written with every episode.
    pub task_index: i64,
}

impl Default for CollectConfig {
    fn default() -> Self {
        Self {
            episodes: 200,
            action_noise: 0.01,
            seed: 0,
            only_success: true,
            max_attempts_per_episode: 20,
            task_index: 0,
        }
    }
}

/// The environment seed of attempt `attempt` under base seed `seed`.
pub fn episode_seed(seed: u64, attempt: u64) -> u64 {
    Rng::derive(seed, attempt).next_u64()
}

/// Progress of a collection, handed to the progress callback after every attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Progress {
    /// Episodes kept so far (including ones already on disk when resuming).
    pub kept: usize,
    /// Episodes wanted in total.
    pub total: usize,
    /// Attempts run in this session.
    pub attempts: usize,
    /// Failed attempts in this session.
    pub failures: usize,
}

/// Summary of one collection session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CollectStats {
    /// Episodes kept in this session.
    pub kept: usize,
    /// Attempts run in this session.
    pub attempts: usize,
    /// Failed attempts in this session.
    pub failures: usize,
    /// Index of the next attempt (to resume from).
    pub next_attempt: u64,
}

/// Run one demonstration episode: observe, ask the expert, execute the label plus noise.
pub fn run_episode<E, X>(
    env: &mut E,
    expert: &mut X,
    seed: u64,
    action_noise: f64,
    task_index: i64,
) -> Episode
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let spec = env.spec();
    let mut ep = Episode::new(spec.fast_dim, spec.slow_dim, spec.action_dim);
    ep.seed = seed;
    ep.task_index = task_index;
    let (mut fast, mut slow) = (vec![0f32; spec.fast_dim], vec![0f32; spec.slow_dim]);
    let (mut label, mut exec) = (vec![0f32; spec.action_dim], vec![0f32; spec.action_dim]);
    let mut noise = Rng::derive(seed, 3);
    env.reset(seed);
    expert.reset(seed);
    for _ in 0..spec.max_steps {
        env.observe(&mut fast, &mut slow);
        expert.act(env, &mut label);
        for (e, l) in exec.iter_mut().zip(&label) {
            *e = (*l as f64 + action_noise * noise.normal() as f64) as f32;
        }
        ep.push(&fast, &slow, &label);
        let r = env.step(&exec);
        if r.done {
            ep.done = true;
            ep.success = r.success;
            break;
        }
    }
    ep
}

/// Collect demonstrations, handing each kept episode to `sink` and reporting progress.
/// `already` episodes count as kept (resume) and attempts start at `first_attempt`.
pub fn collect<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    already: usize,
    first_attempt: u64,
    progress: &mut dyn FnMut(&Progress),
    sink: &mut dyn FnMut(Episode, u64) -> Result<()>,
) -> Result<CollectStats>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let mut p = Progress {
        kept: already,
        total: cfg.episodes,
        attempts: 0,
        failures: 0,
    };
    let mut stats = CollectStats {
        next_attempt: first_attempt,
        ..Default::default()
    };
    let budget = cfg
        .episodes
        .saturating_sub(already)
        .saturating_mul(cfg.max_attempts_per_episode.max(1));
    progress(&p);
    while p.kept < cfg.episodes {
        if p.attempts >= budget {
            return Err(Error::ConfigValue {
                field: "max_attempts_per_episode",
                reason: format!(
                    "gave up after {} attempts with {} of {} episodes kept (the expert fails too often)",
                    p.attempts, p.kept, cfg.episodes
                ),
            });
        }
        let seed = episode_seed(cfg.seed, stats.next_attempt);
        let ep = run_episode(env, expert, seed, cfg.action_noise, cfg.task_index);
        let attempt = stats.next_attempt;
        stats.next_attempt += 1;
        p.attempts += 1;
        if !ep.success {
            p.failures += 1;
        }
        if ep.success || !cfg.only_success {
            sink(ep, attempt)?;
            p.kept += 1;
        }
        progress(&p);
    }
    stats.kept = p.kept - already;
    stats.attempts = p.attempts;
    stats.failures = p.failures;
    Ok(stats)
}

/// Collect demonstrations into memory.
pub fn collect_episodes<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    progress: &mut dyn FnMut(&Progress),
) -> Result<Vec<Episode>>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let mut out = Vec::with_capacity(cfg.episodes);
    collect(env, expert, cfg, 0, 0, progress, &mut |ep, _| {
        out.push(ep);
        Ok(())
    })?;
    Ok(out)
}

/// Collect demonstrations straight into a dataset at `root` (resuming if asked: only the
/// missing episodes are collected, continuing the attempt sequence).
pub fn collect_to_dataset<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    root: &Path,
    spec: &DatasetSpec,
    mode: WriteMode,
    progress: &mut dyn FnMut(&Progress),
) -> Result<(CollectStats, DatasetSummary)>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let mut writer = DatasetWriter::open(root, spec.clone(), mode)?;
    let already = writer.num_episodes();
    let first_attempt = writer.next_attempt();
    let stats = collect(
        env,
        expert,
        cfg,
        already,
        first_attempt,
        progress,
        &mut |ep, attempt| writer.append_attempt(&ep, attempt),
    )?;
    let summary = writer.finish()?;
    Ok((stats, summary))
}

// ------------------------------------------------------------------------------------
// Dataset description
// ------------------------------------------------------------------------------------

/// What a dataset holds: rate, feature names (which fix the widths) and task prompts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetSpec {
    /// Frames per second.
    pub fps: u32,
    /// `robot_type` in `info.json`.
    pub robot_type: Option<String>,
    /// Task prompts; `task_index` indexes this list.
    pub tasks: Vec<String>,
    /// Names of the fast observation entries (`observation.state`).
    pub fast_names: Vec<String>,
    /// Names of the slow observation entries (`observation.environment_state`); empty = none.
    pub slow_names: Vec<String>,
    /// Names of the action entries.
    pub action_names: Vec<String>,
}

impl DatasetSpec {
    /// The ball-on-plate task's dataset.
    pub fn ballplate(fps: u32) -> Self {
        use crate::ballplate::{ACTION_NAMES, FAST_NAMES, SLOW_NAMES};
        let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect();
        Self {
            fps,
            robot_type: Some("pir2_ballplate".into()),
            tasks: vec!["balance the ball at the centre of the plate".into()],
            fast_names: s(&FAST_NAMES),
            slow_names: s(&SLOW_NAMES),
            action_names: s(&ACTION_NAMES),
        }
    }

    /// The `features` object of `info.json`, in column order.
    pub fn features_json(&self) -> Value {
        let mut f = serde_json::Map::new();
        let vec_ft =
            |names: &[String]| json!({"dtype": "float32", "shape": [names.len()], "names": names});
        f.insert(KEY_FAST.into(), vec_ft(&self.fast_names));
        if !self.slow_names.is_empty() {
            f.insert(KEY_SLOW.into(), vec_ft(&self.slow_names));
        }
        f.insert(KEY_ACTION.into(), vec_ft(&self.action_names));
        for (k, dtype) in SCALAR_COLUMNS {
            f.insert(
                k.into(),
                json!({"dtype": dtype, "shape": [1], "names": null}),
            );
        }
        Value::Object(f)
    }
}

/// Scalar frame columns and their LeRobot dtypes, in column order.
const SCALAR_COLUMNS: [(&str, &str); 7] = [
    ("next.done", "bool"),
    ("next.success", "bool"),
    ("timestamp", "float32"),
    ("frame_index", "int64"),
    ("episode_index", "int64"),
    ("index", "int64"),
    ("task_index", "int64"),
];

/// How [`DatasetWriter::open`] treats an existing directory.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WriteMode {
    /// Refuse unless the directory is absent or empty.
    #[default]
    New,
    /// Append to an existing dataset (or start one if absent/empty).
    Resume,
    /// Delete `data/` and `meta/` of an existing dataset, then write anew.
    Overwrite,
}

/// What a finished writing session produced.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetSummary {
    /// Episodes in the dataset.
    pub total_episodes: usize,
    /// Frames in the dataset.
    pub total_frames: usize,
    /// Episodes written in this session.
    pub written_episodes: usize,
    /// Data file written in this session, if any.
    pub data_file: Option<PathBuf>,
}

// ------------------------------------------------------------------------------------
// Writer
// ------------------------------------------------------------------------------------

fn fill_template(template: &str, chunk: usize, file: usize) -> String {
    // Supports `{chunk_index}`, `{file_index}` with an optional `:0Nd` format.
    let mut out = String::with_capacity(template.len());
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let Some(close) = rest[open..].find('}') else {
            out.push_str(&rest[open..]);
            return out;
        };
        let inner = &rest[open + 1..open + close];
        let (name, fmt) = inner.split_once(':').unwrap_or((inner, ""));
        let value = match name {
            "chunk_index" => Some(chunk),
            "file_index" => Some(file),
            _ => None,
        };
        match value {
            Some(v) => {
                let width = fmt
                    .trim_start_matches('0')
                    .trim_end_matches('d')
                    .parse::<usize>()
                    .unwrap_or(0);
                out.push_str(&format!("{v:0width$}"));
            }
            None => out.push_str(&rest[open..open + close + 1]),
        }
        rest = &rest[open + close + 1..];
    }
    out.push_str(rest);
    out
}

fn chunk_file(n: usize) -> (usize, usize) {
    (n / CHUNKS_SIZE, n % CHUNKS_SIZE)
}

fn write_props() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .build()
}

fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

fn create_parent(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    Ok(())
}

fn rename(from: &Path, to: &Path) -> Result<()> {
    fs::rename(from, to).map_err(|e| Error::io(to, e))
}

fn write_batch_file(path: &Path, batch: &RecordBatch) -> Result<()> {
    create_parent(path)?;
    let tmp = tmp_path(path);
    let file = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let mut w = ArrowWriter::try_new(file, batch.schema(), Some(write_props()))
        .map_err(|e| Error::parquet(path, e))?;
    w.write(batch).map_err(|e| Error::parquet(path, e))?;
    w.close().map_err(|e| Error::parquet(path, e))?;
    rename(&tmp, path)
}

fn write_json_file(path: &Path, value: &Value) -> Result<()> {
    create_parent(path)?;
    let tmp = tmp_path(path);
    let text = serde_json::to_string_pretty(value).map_err(|e| Error::json(path, e))?;
    fs::write(&tmp, text + "\n").map_err(|e| Error::io(&tmp, e))?;
    rename(&tmp, path)
}

fn f32_list_field(name: &str, width: usize) -> Field {
    Field::new(
        name,
        DataType::FixedSizeList(
            Arc::new(Field::new_list_field(DataType::Float32, true)),
            width as i32,
        ),
        true,
    )
}

fn f32_list_array(values: Vec<f32>, width: usize, path: &Path) -> Result<ArrayRef> {
    let field = Arc::new(Field::new_list_field(DataType::Float32, true));
    let arr = FixedSizeListArray::try_new(
        field,
        width as i32,
        Arc::new(Float32Array::from(values)),
        None,
    )
    .map_err(|source| Error::Arrow {
        path: path.into(),
        source,
    })?;
    Ok(Arc::new(arr))
}

/// Per-episode bookkeeping, one row of `meta/episodes/*.parquet`.
#[derive(Debug, Clone, PartialEq)]
struct EpisodeRow {
    episode_index: i64,
    tasks: Vec<String>,
    length: i64,
    data_chunk: i64,
    data_file: i64,
    from: i64,
    to: i64,
    meta_chunk: i64,
    meta_file: i64,
    seed: u64,
    success: bool,
    attempt: u64,
}

/// Frames buffered for the current data file.
#[derive(Debug, Default)]
struct FrameBuffer {
    fast: Vec<f32>,
    slow: Vec<f32>,
    action: Vec<f32>,
    done: Vec<bool>,
    success: Vec<bool>,
    timestamp: Vec<f32>,
    frame_index: Vec<i64>,
    episode_index: Vec<i64>,
    index: Vec<i64>,
    task_index: Vec<i64>,
}

/// Writes a LeRobotDataset v3.0 (state-only), one new data file and one new episodes file
/// per session. Episodes are buffered in memory and written by [`DatasetWriter::finish`].
#[derive(Debug)]
pub struct DatasetWriter {
    root: PathBuf,
    spec: DatasetSpec,
    existing: Vec<EpisodeRow>,
    new_rows: Vec<EpisodeRow>,
    frames: FrameBuffer,
    file_no: usize,
    total_frames: i64,
    next_attempt: u64,
}

impl DatasetWriter {
    /// Open `root` for writing according to `mode`.
    pub fn open(root: &Path, spec: DatasetSpec, mode: WriteMode) -> Result<Self> {
        let info_path = root.join(INFO_PATH);
        let non_empty = match fs::read_dir(root) {
            Ok(mut it) => it.next().is_some(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
            Err(e) => return Err(Error::io(root, e)),
        };
        let mut existing = Vec::new();
        match mode {
            WriteMode::New if non_empty => {
                let what = if info_path.exists() {
                    "meta/info.json found"
                } else {
                    "directory is not empty"
                };
                return Err(Error::AlreadyExists {
                    path: root.into(),
                    what: what.into(),
                });
            }
            WriteMode::Resume if non_empty => {
                if !info_path.exists() {
                    return Err(Error::AlreadyExists {
                        path: root.into(),
                        what: "directory is not empty but has no meta/info.json, so it cannot be resumed".into(),
                    });
                }
                let info = read_info(root)?;
                check_compatible(&info_path, &info, &spec)?;
                existing = read_episode_rows(root)?;
                // LeRobot loads every `data/*/*.parquet`: a data file that no episode row
                // references (left by an interrupted session) would corrupt the dataset.
                let referenced: std::collections::BTreeSet<usize> = existing
                    .iter()
                    .map(|r| r.data_chunk as usize * CHUNKS_SIZE + r.data_file as usize)
                    .collect();
                for n in file_numbers(&root.join("data"), true)? {
                    if !referenced.contains(&n) {
                        let (c, f) = chunk_file(n);
                        return Err(Error::Inconsistent {
                            path: root.join(fill_template(DATA_PATH, c, f)),
                            reason: "data file not referenced by meta/episodes (left by an interrupted session?); \
                                     remove it, or rewrite the dataset with WriteMode::Overwrite"
                                .into(),
                        });
                    }
                }
            }
            WriteMode::Overwrite => {
                for sub in ["data", "meta"] {
                    let p = root.join(sub);
                    if p.exists() {
                        fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
                    }
                }
            }
            _ => {}
        }
        // Never reuse a file number that is on disk (even an orphan from an interrupted run).
        let mut file_no = 0;
        for dir in ["data", "meta/episodes"] {
            if let Some(max) = max_file_number(&root.join(dir))? {
                file_no = file_no.max(max + 1);
            }
        }
        let total_frames = existing.iter().map(|r| r.to).max().unwrap_or(0);
        let next_attempt = existing.iter().map(|r| r.attempt + 1).max().unwrap_or(0);
        Ok(Self {
            root: root.into(),
            spec,
            existing,
            new_rows: Vec::new(),
            frames: FrameBuffer::default(),
            file_no,
            total_frames,
            next_attempt,
        })
    }

    /// Episodes in the dataset including the ones appended in this session.
    pub fn num_episodes(&self) -> usize {
        self.existing.len() + self.new_rows.len()
    }

    /// Attempt index to continue a seeded collection from (see [`collect_to_dataset`]).
    pub fn next_attempt(&self) -> u64 {
        self.next_attempt
    }

    /// Append one episode (buffered until [`DatasetWriter::finish`]).
    pub fn append(&mut self, ep: &Episode) -> Result<()> {
        self.append_attempt(ep, self.next_attempt)
    }

    /// Append one episode produced by collection attempt `attempt` (stored as
    /// `pir2/attempt`, so that a resumed collection continues the seed sequence).
    pub fn append_attempt(&mut self, ep: &Episode, attempt: u64) -> Result<()> {
        let episode_index = self.num_episodes() as i64;
        ep.check(episode_index as usize, &self.spec)?;
        let n = ep.len();
        let f = &mut self.frames;
        f.fast.extend_from_slice(&ep.fast);
        f.slow.extend_from_slice(&ep.slow);
        f.action.extend_from_slice(&ep.action);
        let dt = 1.0 / self.spec.fps as f64;
        for t in 0..n {
            let last = t + 1 == n;
            f.done.push(last && ep.done);
            f.success.push(last && ep.done && ep.success);
            f.timestamp.push((t as f64 * dt) as f32);
            f.frame_index.push(t as i64);
            f.episode_index.push(episode_index);
            f.index.push(self.total_frames + t as i64);
            f.task_index.push(ep.task_index);
        }
        let (chunk, file) = chunk_file(self.file_no);
        self.new_rows.push(EpisodeRow {
            episode_index,
            tasks: vec![self.spec.tasks[ep.task_index as usize].clone()],
            length: n as i64,
            data_chunk: chunk as i64,
            data_file: file as i64,
            from: self.total_frames,
            to: self.total_frames + n as i64,
            meta_chunk: chunk as i64,
            meta_file: file as i64,
            seed: ep.seed,
            success: ep.success,
            attempt,
        });
        self.next_attempt = self.next_attempt.max(attempt + 1);
        self.total_frames += n as i64;
        Ok(())
    }

    fn data_batch(&mut self, path: &Path) -> Result<RecordBatch> {
        let spec = &self.spec;
        let f = std::mem::take(&mut self.frames);
        let mut fields = vec![f32_list_field(KEY_FAST, spec.fast_names.len())];
        let mut cols = vec![f32_list_array(f.fast, spec.fast_names.len(), path)?];
        if !spec.slow_names.is_empty() {
            fields.push(f32_list_field(KEY_SLOW, spec.slow_names.len()));
            cols.push(f32_list_array(f.slow, spec.slow_names.len(), path)?);
        }
        fields.push(f32_list_field(KEY_ACTION, spec.action_names.len()));
        cols.push(f32_list_array(f.action, spec.action_names.len(), path)?);
        fields.push(Field::new("next.done", DataType::Boolean, true));
        cols.push(Arc::new(BooleanArray::from(f.done)));
        fields.push(Field::new("next.success", DataType::Boolean, true));
        cols.push(Arc::new(BooleanArray::from(f.success)));
        fields.push(Field::new("timestamp", DataType::Float32, true));
        cols.push(Arc::new(Float32Array::from(f.timestamp)));
        for (name, v) in [
            ("frame_index", f.frame_index),
            ("episode_index", f.episode_index),
            ("index", f.index),
            ("task_index", f.task_index),
        ] {
            fields.push(Field::new(name, DataType::Int64, true));
            cols.push(Arc::new(Int64Array::from(v)));
        }
        RecordBatch::try_new(Arc::new(Schema::new(fields)), cols).map_err(|source| Error::Arrow {
            path: path.into(),
            source,
        })
    }

    /// Write the data and episodes files of this session, then `tasks.parquet`,
    /// `stats.json` (recomputed over the whole dataset) and `info.json`.
    pub fn finish(mut self) -> Result<DatasetSummary> {
        let (chunk, file) = chunk_file(self.file_no);
        let mut data_file = None;
        if !self.new_rows.is_empty() {
            let data_path = self.root.join(fill_template(DATA_PATH, chunk, file));
            let batch = self.data_batch(&data_path)?;
            write_batch_file(&data_path, &batch)?;
            data_file = Some(data_path);
        }
        let all: Vec<EpisodeRow> = self
            .existing
            .iter()
            .chain(&self.new_rows)
            .cloned()
            .collect();
        // Stats over every frame of the dataset, and per episode for the episodes table.
        let loaded = read_frames(&self.root, &all)?;
        if !self.new_rows.is_empty() {
            let ep_path = self.root.join(fill_template(EPISODES_PATH, chunk, file));
            let new_eps = &loaded[self.existing.len()..];
            let batch = episodes_batch(&ep_path, &self.new_rows, new_eps, &self.spec)?;
            write_batch_file(&ep_path, &batch)?;
        }
        write_tasks(&self.root.join(TASKS_PATH), &self.spec.tasks)?;
        let stats = dataset_stats(&loaded, &self.spec);
        write_json_file(&self.root.join(STATS_PATH), &stats)?;
        let total_frames = all.iter().map(|r| r.length).sum::<i64>() as usize;
        let info = json!({
            "codebase_version": CODEBASE_VERSION,
            "robot_type": self.spec.robot_type,
            "total_episodes": all.len(),
            "total_frames": total_frames,
            "total_tasks": self.spec.tasks.len(),
            "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 500,
            "fps": self.spec.fps,
            "splits": {"train": format!("0:{}", all.len())},
            "data_path": DATA_PATH,
            "video_path": null,
            "features": self.spec.features_json(),
        });
        write_json_file(&self.root.join(INFO_PATH), &info)?;
        Ok(DatasetSummary {
            total_episodes: all.len(),
            total_frames,
            written_episodes: self.new_rows.len(),
            data_file,
        })
    }
}

fn max_file_number(dir: &Path) -> Result<Option<usize>> {
    Ok(file_numbers(dir, false)?.into_iter().max())
}

/// Numbers (`chunk · CHUNKS_SIZE + file`) of the `chunk-*/file-*` files under `dir`; with
/// `parquet_only`, only finished `.parquet` files (not `.tmp` leftovers).
fn file_numbers(dir: &Path, parquet_only: bool) -> Result<Vec<usize>> {
    let mut out = Vec::new();
    let Ok(chunks) = fs::read_dir(dir) else {
        return Ok(out);
    };
    for c in chunks {
        let c = c.map_err(|e| Error::io(dir, e))?;
        let cname = c.file_name().to_string_lossy().into_owned();
        let Some(ci) = cname
            .strip_prefix("chunk-")
            .and_then(|s| s.parse::<usize>().ok())
        else {
            continue;
        };
        let Ok(files) = fs::read_dir(c.path()) else {
            continue;
        };
        for f in files {
            let f = f.map_err(|e| Error::io(c.path(), e))?;
            let fname = f.file_name().to_string_lossy().into_owned();
            if parquet_only && !fname.ends_with(".parquet") {
                continue;
            }
            let Some(fi) = fname
                .strip_prefix("file-")
                .and_then(|s| s.split('.').next()?.parse::<usize>().ok())
            else {
                continue;
            };
            out.push(ci * CHUNKS_SIZE + fi);
        }
    }
    out.sort_unstable();
    Ok(out)
}

fn check_compatible(path: &Path, info: &Value, spec: &DatasetSpec) -> Result<()> {
    let want = spec.features_json();
    let have = info.get("features").cloned().unwrap_or(Value::Null);
    if have != want {
        return Err(Error::Inconsistent {
            path: path.into(),
            reason: format!("features differ from the episodes to append:\n  on disk: {have}\n  new:     {want}"),
        });
    }
    if info.get("fps").and_then(Value::as_f64) != Some(spec.fps as f64) {
        return Err(Error::Inconsistent {
            path: path.into(),
            reason: format!("fps differs (new: {})", spec.fps),
        });
    }
    Ok(())
}

fn write_tasks(path: &Path, tasks: &[String]) -> Result<()> {
    // pandas metadata so that `pd.read_parquet` restores `task` as the index, as LeRobot's
    // `write_tasks` (DataFrame indexed by task) produces.
    let pandas = json!({
        "index_columns": ["task"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "creator": {"library": "pir2-sim", "version": env!("CARGO_PKG_VERSION")},
        "pandas_version": "2.2.0"
    });
    let metadata = [("pandas".to_string(), pandas.to_string())]
        .into_iter()
        .collect();
    let schema = Schema::new(vec![
        Field::new("task_index", DataType::Int64, true),
        Field::new("task", DataType::Utf8, true),
    ])
    .with_metadata(metadata);
    let batch = RecordBatch::try_new(
        Arc::new(schema),
        vec![
            Arc::new(Int64Array::from_iter_values(0..tasks.len() as i64)),
            Arc::new(StringArray::from_iter_values(tasks.iter())),
        ],
    )
    .map_err(|source| Error::Arrow {
        path: path.into(),
        source,
    })?;
    write_batch_file(path, &batch)
}

// ------------------------------------------------------------------------------------
// Statistics
// ------------------------------------------------------------------------------------

/// Per-dimension statistics of one feature (LeRobot's `get_feature_stats` + quantiles).
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    /// Minimum per dimension.
    pub min: Vec<f64>,
    /// Maximum per dimension.
    pub max: Vec<f64>,
    /// Mean per dimension.
    pub mean: Vec<f64>,
    /// Population standard deviation per dimension (numpy's `std`).
    pub std: Vec<f64>,
    /// Number of frames.
    pub count: usize,
    /// Quantiles per dimension, in the order of [`QUANTILES`].
    pub quantiles: Vec<Vec<f64>>,
}

impl FeatureStats {
    /// Statistics of `n = data.len() / dim` rows of width `dim`.
    pub fn compute(data: &[f64], dim: usize) -> Self {
        let n = data.len().checked_div(dim).unwrap_or(0);
        let mut s = Self {
            min: vec![f64::INFINITY; dim],
            max: vec![f64::NEG_INFINITY; dim],
            mean: vec![0.0; dim],
            std: vec![0.0; dim],
            count: n,
            quantiles: vec![vec![0.0; dim]; QUANTILES.len()],
        };
        let mut col = Vec::with_capacity(n);
        for d in 0..dim {
            col.clear();
            col.extend((0..n).map(|t| data[t * dim + d]));
            let mean = col.iter().sum::<f64>() / n.max(1) as f64;
            let var = col.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n.max(1) as f64;
            s.mean[d] = mean;
            s.std[d] = var.sqrt();
            col.sort_by(|a, b| a.total_cmp(b));
            if let (Some(lo), Some(hi)) = (col.first(), col.last()) {
                s.min[d] = *lo;
                s.max[d] = *hi;
            }
            for (qi, (q, _)) in QUANTILES.iter().enumerate() {
                s.quantiles[qi][d] = quantile_sorted(&col, *q);
            }
        }
        s
    }

    /// The JSON object written to `stats.json`.
    pub fn to_json(&self) -> Value {
        let mut m = serde_json::Map::new();
        m.insert("min".into(), json!(self.min));
        m.insert("max".into(), json!(self.max));
        m.insert("mean".into(), json!(self.mean));
        m.insert("std".into(), json!(self.std));
        m.insert("count".into(), json!([self.count]));
        for (qi, (_, name)) in QUANTILES.iter().enumerate() {
            m.insert((*name).into(), json!(self.quantiles[qi]));
        }
        Value::Object(m)
    }
}

/// Linear-interpolation quantile of sorted data (numpy's default method).
fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    match sorted.len() {
        0 => f64::NAN,
        1 => sorted[0],
        n => {
            let pos = q * (n - 1) as f64;
            let lo = pos.floor() as usize;
            let hi = (lo + 1).min(n - 1);
            sorted[lo] + (pos - lo as f64) * (sorted[hi] - sorted[lo])
        }
    }
}

/// Every numeric feature of a set of episodes as `(key, rows, width)`, in column order.
fn feature_columns<'a>(
    eps: impl Iterator<Item = &'a Episode> + Clone,
    spec: &DatasetSpec,
) -> Vec<(&'static str, Vec<f64>, usize)> {
    let mut out = Vec::new();
    let widen = |v: &[f32]| v.iter().map(|x| *x as f64).collect::<Vec<_>>();
    out.push((
        KEY_FAST,
        eps.clone().flat_map(|e| widen(&e.fast)).collect(),
        spec.fast_names.len(),
    ));
    if !spec.slow_names.is_empty() {
        out.push((
            KEY_SLOW,
            eps.clone().flat_map(|e| widen(&e.slow)).collect(),
            spec.slow_names.len(),
        ));
    }
    out.push((
        KEY_ACTION,
        eps.clone().flat_map(|e| widen(&e.action)).collect(),
        spec.action_names.len(),
    ));
    let per_frame = |f: &dyn Fn(&Episode, usize) -> f64| -> Vec<f64> {
        eps.clone()
            .flat_map(|e| (0..e.len()).map(move |t| f(e, t)).collect::<Vec<_>>())
            .collect()
    };
    let last = |e: &Episode, t: usize| t + 1 == e.len();
    out.push((
        "next.done",
        per_frame(&|e, t| f64::from(u8::from(last(e, t) && e.done))),
        1,
    ));
    out.push((
        "next.success",
        per_frame(&|e, t| f64::from(u8::from(last(e, t) && e.done && e.success))),
        1,
    ));
    let fps = spec.fps as f64;
    out.push((
        "timestamp",
        per_frame(&|_, t| (t as f64 / fps) as f32 as f64),
        1,
    ));
    out.push(("frame_index", per_frame(&|_, t| t as f64), 1));
    out
}

fn dataset_stats(eps: &[LoadedEpisode], spec: &DatasetSpec) -> Value {
    let mut m = serde_json::Map::new();
    for (key, data, dim) in feature_columns(eps.iter().map(|l| &l.episode), spec) {
        m.insert(key.into(), FeatureStats::compute(&data, dim).to_json());
    }
    // Index columns: episode_index, index, task_index.
    let ep_idx: Vec<f64> = eps
        .iter()
        .flat_map(|l| std::iter::repeat_n(l.episode_index as f64, l.episode.len()))
        .collect();
    m.insert(
        "episode_index".into(),
        FeatureStats::compute(&ep_idx, 1).to_json(),
    );
    let index: Vec<f64> = eps
        .iter()
        .flat_map(|l| (0..l.episode.len()).map(move |t| (l.from + t as i64) as f64))
        .collect();
    m.insert("index".into(), FeatureStats::compute(&index, 1).to_json());
    let task: Vec<f64> = eps
        .iter()
        .flat_map(|l| std::iter::repeat_n(l.episode.task_index as f64, l.episode.len()))
        .collect();
    m.insert(
        "task_index".into(),
        FeatureStats::compute(&task, 1).to_json(),
    );
    Value::Object(m)
}

fn list_f64_array(rows: Vec<Vec<f64>>) -> ArrayRef {
    Arc::new(ListArray::from_iter_primitive::<Float64Type, _, _>(
        rows.into_iter().map(|r| Some(r.into_iter().map(Some))),
    ))
}

fn episodes_batch(
    path: &Path,
    rows: &[EpisodeRow],
    eps: &[LoadedEpisode],
    spec: &DatasetSpec,
) -> Result<RecordBatch> {
    let mut fields = Vec::new();
    let mut cols: Vec<ArrayRef> = Vec::new();
    let i64_col = |fields: &mut Vec<Field>,
                   cols: &mut Vec<ArrayRef>,
                   name: &str,
                   f: &dyn Fn(&EpisodeRow) -> i64| {
        fields.push(Field::new(name, DataType::Int64, true));
        cols.push(Arc::new(Int64Array::from_iter_values(rows.iter().map(f))));
    };
    i64_col(&mut fields, &mut cols, "episode_index", &|r| {
        r.episode_index
    });
    let mut tasks = ListBuilder::new(StringBuilder::new());
    for r in rows {
        for t in &r.tasks {
            tasks.values().append_value(t);
        }
        tasks.append(true);
    }
    let tasks = tasks.finish();
    fields.push(Field::new("tasks", tasks.data_type().clone(), true));
    cols.push(Arc::new(tasks));
    i64_col(&mut fields, &mut cols, "length", &|r| r.length);
    i64_col(&mut fields, &mut cols, "data/chunk_index", &|r| {
        r.data_chunk
    });
    i64_col(&mut fields, &mut cols, "data/file_index", &|r| r.data_file);
    i64_col(&mut fields, &mut cols, "dataset_from_index", &|r| r.from);
    i64_col(&mut fields, &mut cols, "dataset_to_index", &|r| r.to);
    i64_col(&mut fields, &mut cols, "meta/episodes/chunk_index", &|r| {
        r.meta_chunk
    });
    i64_col(&mut fields, &mut cols, "meta/episodes/file_index", &|r| {
        r.meta_file
    });
    // Per-episode stats, flattened as LeRobot does: `stats/<feature>/<stat>`.
    let per_ep: Vec<Vec<(&'static str, FeatureStats)>> = eps
        .iter()
        .map(|l| {
            let n = l.episode.len();
            let mut cols = feature_columns(std::iter::once(&l.episode), spec);
            // The index columns too, as LeRobot's `compute_episode_stats` covers every feature.
            cols.push(("episode_index", vec![l.episode_index as f64; n], 1));
            cols.push((
                "index",
                (0..n).map(|t| (l.from + t as i64) as f64).collect(),
                1,
            ));
            cols.push(("task_index", vec![l.episode.task_index as f64; n], 1));
            cols.into_iter()
                .map(|(k, data, dim)| (k, FeatureStats::compute(&data, dim)))
                .collect::<Vec<_>>()
        })
        .collect();
    if let Some(first) = per_ep.first() {
        for (fi, (key, _)) in first.iter().enumerate() {
            let pick = |f: &dyn Fn(&FeatureStats) -> Vec<f64>| -> Vec<Vec<f64>> {
                per_ep.iter().map(|e| f(&e[fi].1)).collect()
            };
            let mut stat_cols: Vec<(String, ArrayRef)> = vec![
                ("min".into(), list_f64_array(pick(&|s| s.min.clone()))),
                ("max".into(), list_f64_array(pick(&|s| s.max.clone()))),
                ("mean".into(), list_f64_array(pick(&|s| s.mean.clone()))),
                ("std".into(), list_f64_array(pick(&|s| s.std.clone()))),
            ];
            let counts = per_ep
                .iter()
                .map(|e| Some(vec![Some(e[fi].1.count as i64)]));
            stat_cols.push((
                "count".into(),
                Arc::new(ListArray::from_iter_primitive::<Int64Type, _, _>(counts)),
            ));
            for (qi, (_, qname)) in QUANTILES.iter().enumerate() {
                stat_cols.push((
                    (*qname).into(),
                    list_f64_array(pick(&|s| s.quantiles[qi].clone())),
                ));
            }
            for (stat, arr) in stat_cols {
                fields.push(Field::new(
                    format!("stats/{key}/{stat}"),
                    arr.data_type().clone(),
                    true,
                ));
                cols.push(arr);
            }
        }
    }
    fields.push(Field::new("pir2/seed", DataType::UInt64, true));
    cols.push(Arc::new(UInt64Array::from_iter_values(
        rows.iter().map(|r| r.seed),
    )));
    fields.push(Field::new("pir2/success", DataType::Boolean, true));
    cols.push(Arc::new(BooleanArray::from(
        rows.iter().map(|r| r.success).collect::<Vec<_>>(),
    )));
    fields.push(Field::new("pir2/attempt", DataType::UInt64, true));
    cols.push(Arc::new(UInt64Array::from_iter_values(
        rows.iter().map(|r| r.attempt),
    )));
    RecordBatch::try_new(Arc::new(Schema::new(fields)), cols).map_err(|source| Error::Arrow {
        path: path.into(),
        source,
    })
}

// ------------------------------------------------------------------------------------
// Reader
// ------------------------------------------------------------------------------------

/// A dataset loaded into memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// Frames per second (`info.json`).
    pub fps: f64,
    /// `meta/info.json` as parsed.
    pub info: Value,
    /// Task prompts by `task_index` (empty if `meta/tasks.parquet` is absent).
    pub tasks: Vec<String>,
    /// Episodes in `episode_index` order.
    pub episodes: Vec<Episode>,
}

impl Dataset {
    /// Total frames.
    pub fn total_frames(&self) -> usize {
        self.episodes.iter().map(Episode::len).sum()
    }
}

/// An episode read back, with where it sits in the dataset.
#[derive(Debug, Clone)]
struct LoadedEpisode {
    episode_index: i64,
    from: i64,
    episode: Episode,
}

fn read_info(root: &Path) -> Result<Value> {
    let path = root.join(INFO_PATH);
    let text = match fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(Error::MissingFile { path })
        }
        Err(e) => return Err(Error::io(path, e)),
    };
    serde_json::from_str(&text).map_err(|e| Error::json(path, e))
}

fn read_parquet(path: &Path) -> Result<Vec<RecordBatch>> {
    let file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(Error::MissingFile { path: path.into() })
        }
        Err(e) => return Err(Error::io(path, e)),
    };
    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
        .map_err(|e| Error::parquet(path, e))?
        .build()
        .map_err(|e| Error::parquet(path, e))?;
    reader
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|source| Error::Arrow {
            path: path.into(),
            source,
        })
}

fn column<'a>(batch: &'a RecordBatch, path: &Path, name: &str) -> Result<&'a ArrayRef> {
    batch
        .column_by_name(name)
        .ok_or_else(|| Error::MissingColumn {
            path: path.into(),
            column: name.into(),
        })
}

fn type_error(path: &Path, name: &str, expected: &str, found: &DataType) -> Error {
    Error::ColumnType {
        path: path.into(),
        column: name.into(),
        expected: expected.into(),
        found: found.to_string(),
    }
}

/// An integer column as `i64` (accepts int32/int64/uint64).
fn int_column(batch: &RecordBatch, path: &Path, name: &str) -> Result<Vec<i64>> {
    let a = column(batch, path, name)?;
    let v = match a.data_type() {
        DataType::Int64 => a.as_primitive::<Int64Type>().values().to_vec(),
        DataType::Int32 => a
            .as_primitive::<Int32Type>()
            .values()
            .iter()
            .map(|v| *v as i64)
            .collect(),
        DataType::UInt64 => a
            .as_primitive::<UInt64Type>()
            .values()
            .iter()
            .map(|v| *v as i64)
            .collect(),
        t => return Err(type_error(path, name, "int64", t)),
    };
    Ok(v)
}

/// A vector feature column as row-major `f32` plus its width. Accepts fixed-size and
/// variable-size lists of `float32`/`float64` (every row must have the same width).
fn vec_column(batch: &RecordBatch, path: &Path, name: &str) -> Result<(Vec<f32>, usize)> {
    let a = column(batch, path, name)?;
    let expected = "list<float32|float64> of a fixed width";
    let to_f32 = |values: &ArrayRef| -> Result<Vec<f32>> {
        match values.data_type() {
            DataType::Float32 => Ok(values.as_primitive::<Float32Type>().values().to_vec()),
            DataType::Float64 => Ok(values
                .as_primitive::<Float64Type>()
                .values()
                .iter()
                .map(|v| *v as f32)
                .collect()),
            _ => Err(type_error(path, name, expected, a.data_type())),
        }
    };
    if a.null_count() > 0 {
        return Err(type_error(path, name, "no null rows", a.data_type()));
    }
    match a.data_type() {
        DataType::FixedSizeList(_, w) => {
            let l = a.as_fixed_size_list();
            let values = l
                .values()
                .slice(l.offset() * *w as usize, l.len() * *w as usize);
            Ok((to_f32(&values)?, *w as usize))
        }
        DataType::List(_) | DataType::LargeList(_) => {
            let offsets: Vec<usize> = match a.data_type() {
                DataType::List(_) => a
                    .as_list::<i32>()
                    .offsets()
                    .iter()
                    .map(|o| *o as usize)
                    .collect(),
                _ => a
                    .as_list::<i64>()
                    .offsets()
                    .iter()
                    .map(|o| *o as usize)
                    .collect(),
            };
            let values = match a.data_type() {
                DataType::List(_) => a.as_list::<i32>().values().clone(),
                _ => a.as_list::<i64>().values().clone(),
            };
            let width = offsets.windows(2).next().map_or(0, |w| w[1] - w[0]);
            if offsets.windows(2).any(|w| w[1] - w[0] != width) {
                return Err(type_error(path, name, expected, a.data_type()));
            }
            let (lo, hi) = (offsets[0], offsets[offsets.len() - 1]);
            Ok((to_f32(&values.slice(lo, hi - lo))?, width))
        }
        DataType::Float32 | DataType::Float64 => Ok((to_f32(a)?, 1)),
        t => Err(type_error(path, name, expected, t)),
    }
}

fn bool_column(batch: &RecordBatch, path: &Path, name: &str) -> Result<Option<Vec<bool>>> {
    match batch.column_by_name(name) {
        None => Ok(None),
        Some(a) => match a.data_type() {
            DataType::Boolean => Ok(Some(
                a.as_boolean().iter().map(|v| v.unwrap_or(false)).collect(),
            )),
            t => Err(type_error(path, name, "bool", t)),
        },
    }
}

fn read_episode_rows(root: &Path) -> Result<Vec<EpisodeRow>> {
    let dir = root.join("meta/episodes");
    let mut files = Vec::new();
    if let Ok(chunks) = fs::read_dir(&dir) {
        for c in chunks {
            let c = c.map_err(|e| Error::io(&dir, e))?;
            if let Ok(fs_) = fs::read_dir(c.path()) {
                for f in fs_ {
                    let p = f.map_err(|e| Error::io(c.path(), e))?.path();
                    if p.extension().is_some_and(|e| e == "parquet") {
                        files.push(p);
                    }
                }
            }
        }
    }
    if files.is_empty() {
        return Err(Error::MissingFile {
            path: dir.join("chunk-000/file-000.parquet"),
        });
    }
    files.sort();
    let mut rows = Vec::new();
    for path in files {
        for b in read_parquet(&path)? {
            let n = b.num_rows();
            let ep = int_column(&b, &path, "episode_index")?;
            let length = int_column(&b, &path, "length")?;
            let dchunk = int_column(&b, &path, "data/chunk_index")?;
            let dfile = int_column(&b, &path, "data/file_index")?;
            let opt_int = |name: &str| -> Result<Option<Vec<i64>>> {
                if b.column_by_name(name).is_some() {
                    int_column(&b, &path, name).map(Some)
                } else {
                    Ok(None)
                }
            };
            let from = opt_int("dataset_from_index")?;
            let to = opt_int("dataset_to_index")?;
            let mchunk = opt_int("meta/episodes/chunk_index")?;
            let mfile = opt_int("meta/episodes/file_index")?;
            let seed = opt_int("pir2/seed")?;
            let attempt = opt_int("pir2/attempt")?;
            let success = bool_column(&b, &path, "pir2/success")?;
            let tasks: Vec<Vec<String>> = match b.column_by_name("tasks") {
                Some(a) => match a.data_type() {
                    DataType::List(f) if f.data_type() == &DataType::Utf8 => {
                        let l = a.as_list::<i32>();
                        (0..n)
                            .map(|i| {
                                let v = l.value(i);
                                v.as_string::<i32>()
                                    .iter()
                                    .map(|s| s.unwrap_or_default().to_string())
                                    .collect()
                            })
                            .collect()
                    }
                    t => return Err(type_error(&path, "tasks", "list<string>", t)),
                },
                None => vec![Vec::new(); n],
            };
            for i in 0..n {
                rows.push(EpisodeRow {
                    episode_index: ep[i],
                    tasks: tasks[i].clone(),
                    length: length[i],
                    data_chunk: dchunk[i],
                    data_file: dfile[i],
                    from: from.as_ref().map_or(-1, |v| v[i]),
                    to: to.as_ref().map_or(-1, |v| v[i]),
                    meta_chunk: mchunk.as_ref().map_or(0, |v| v[i]),
                    meta_file: mfile.as_ref().map_or(0, |v| v[i]),
                    seed: seed.as_ref().map_or(0, |v| v[i] as u64),
                    success: success.as_ref().is_some_and(|v| v[i]),
                    attempt: attempt.as_ref().map_or(ep[i] as u64, |v| v[i] as u64),
                });
            }
        }
    }
    rows.sort_by_key(|r| r.episode_index);
    // Fill in missing global indices (older writers) from the lengths.
    let mut acc = 0;
    for r in &mut rows {
        if r.from < 0 || r.to < 0 {
            r.from = acc;
            r.to = acc + r.length;
        }
        acc = r.to;
    }
    Ok(rows)
}

/// Which columns hold the fast/slow/action features (ours by default; LeRobot datasets of
/// other robots may name theirs differently).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadOptions {
    /// Column of the fast observation.
    pub fast_key: String,
    /// Column of the slow observation; absent from the file = no slow channel.
    pub slow_key: String,
    /// Column of the action.
    pub action_key: String,
}

impl Default for ReadOptions {
    fn default() -> Self {
        Self {
            fast_key: KEY_FAST.into(),
            slow_key: KEY_SLOW.into(),
            action_key: KEY_ACTION.into(),
        }
    }
}

/// Read the frames of the given episodes (grouped by their data files).
fn read_frames(root: &Path, rows: &[EpisodeRow]) -> Result<Vec<LoadedEpisode>> {
    read_frames_with(root, DATA_PATH, rows, &ReadOptions::default())
}

fn read_frames_with(
    root: &Path,
    data_tmpl: &str,
    rows: &[EpisodeRow],
    opts: &ReadOptions,
) -> Result<Vec<LoadedEpisode>> {
    let mut files: BTreeMap<(i64, i64), ()> = BTreeMap::new();
    for r in rows {
        files.insert((r.data_chunk, r.data_file), ());
    }
    let mut by_ep: BTreeMap<i64, (Episode, Vec<i64>)> = BTreeMap::new();
    for &(chunk, file) in files.keys() {
        let path = root.join(fill_template(data_tmpl, chunk as usize, file as usize));
        for b in read_parquet(&path)? {
            let (fast, fd) = vec_column(&b, &path, &opts.fast_key)?;
            let (slow, sd) = if b.column_by_name(&opts.slow_key).is_some() {
                vec_column(&b, &path, &opts.slow_key)?
            } else {
                (Vec::new(), 0)
            };
            let (action, ad) = vec_column(&b, &path, &opts.action_key)?;
            let ep_idx = int_column(&b, &path, "episode_index")?;
            let frame = int_column(&b, &path, "frame_index")?;
            let task = if b.column_by_name("task_index").is_some() {
                int_column(&b, &path, "task_index")?
            } else {
                vec![0; b.num_rows()]
            };
            for i in 0..b.num_rows() {
                let (ep, frames) = by_ep.entry(ep_idx[i]).or_insert_with(|| {
                    let mut e = Episode::new(fd, sd, ad);
                    e.task_index = task[i];
                    (e, Vec::new())
                });
                ep.push(
                    &fast[i * fd..(i + 1) * fd],
                    &slow[i * sd..(i + 1) * sd],
                    &action[i * ad..(i + 1) * ad],
                );
                frames.push(frame[i]);
            }
        }
    }
    let mut out = Vec::with_capacity(rows.len());
    for r in rows {
        let data_path = root.join(fill_template(
            data_tmpl,
            r.data_chunk as usize,
            r.data_file as usize,
        ));
        let Some((mut ep, frames)) = by_ep.remove(&r.episode_index) else {
            return Err(Error::Inconsistent {
                path: data_path,
                reason: format!(
                    "episode {} listed in meta/episodes has no frames",
                    r.episode_index
                ),
            });
        };
        if ep.len() as i64 != r.length {
            return Err(Error::Inconsistent {
                path: data_path,
                reason: format!(
                    "episode {} has {} frames, meta/episodes says {}",
                    r.episode_index,
                    ep.len(),
                    r.length
                ),
            });
        }
        if frames.iter().enumerate().any(|(t, f)| *f != t as i64) {
            return Err(Error::Inconsistent {
                path: data_path,
                reason: format!(
                    "episode {}: frame_index is not 0, 1, 2, … in file order",
                    r.episode_index
                ),
            });
        }
        ep.seed = r.seed;
        ep.success = r.success;
        ep.done = r.success;
        out.push(LoadedEpisode {
            episode_index: r.episode_index,
            from: r.from,
            episode: ep,
        });
    }
    Ok(out)
}

/// Read a LeRobotDataset v3.0 at `root` into memory (our column names).
pub fn read_dataset(root: &Path) -> Result<Dataset> {
    read_dataset_with(root, &ReadOptions::default())
}

/// Read a LeRobotDataset v3.0 at `root` into memory, with the given feature columns.
/// `episode_index`, `frame_index` and the `meta/episodes` table are required; `next.done`
/// and `next.success` are used when present.
pub fn read_dataset_with(root: &Path, opts: &ReadOptions) -> Result<Dataset> {
    let info = read_info(root)?;
    let info_path = root.join(INFO_PATH);
    let version = info
        .get("codebase_version")
        .and_then(Value::as_str)
        .unwrap_or("");
    if !version.starts_with("v3.") {
        return Err(Error::Inconsistent {
            path: info_path,
            reason: format!("codebase_version is {version:?}; this reader handles the v3.x layout"),
        });
    }
    let fps = info
        .get("fps")
        .and_then(Value::as_f64)
        .ok_or_else(|| Error::Inconsistent {
            path: info_path.clone(),
            reason: "no numeric `fps`".into(),
        })?;
    let data_tmpl = info
        .get("data_path")
        .and_then(Value::as_str)
        .unwrap_or(DATA_PATH)
        .to_string();
    let rows = read_episode_rows(root)?;
    let mut loaded = read_frames_with(root, &data_tmpl, &rows, opts)?;
    // Done/success flags from the `next.*` frame columns when present.
    fill_flags_from_frames(root, &data_tmpl, &rows, &mut loaded)?;
    let tasks_path = root.join(TASKS_PATH);
    let tasks = if tasks_path.exists() {
        read_tasks(&tasks_path)?
    } else {
        Vec::new()
    };
    Ok(Dataset {
        fps,
        info,
        tasks,
        episodes: loaded.into_iter().map(|l| l.episode).collect(),
    })
}

fn fill_flags_from_frames(
    root: &Path,
    tmpl: &str,
    rows: &[EpisodeRow],
    loaded: &mut [LoadedEpisode],
) -> Result<()> {
    let mut files: BTreeMap<(i64, i64), ()> = BTreeMap::new();
    for r in rows {
        files.insert((r.data_chunk, r.data_file), ());
    }
    let mut last: BTreeMap<i64, (bool, bool)> = BTreeMap::new();
    for &(chunk, file) in files.keys() {
        let path = root.join(fill_template(tmpl, chunk as usize, file as usize));
        for b in read_parquet(&path)? {
            let (Some(done), success) = (
                bool_column(&b, &path, "next.done")?,
                bool_column(&b, &path, "next.success")?,
            ) else {
                return Ok(());
            };
            let ep = int_column(&b, &path, "episode_index")?;
            for i in 0..b.num_rows() {
                let e = last.entry(ep[i]).or_default();
                e.0 |= done[i];
                e.1 |= success.as_ref().is_some_and(|s| s[i]);
            }
        }
    }
    for l in loaded {
        if let Some((d, s)) = last.get(&l.episode_index) {
            l.episode.done = *d;
            l.episode.success = l.episode.success || *s;
        }
    }
    Ok(())
}

fn read_tasks(path: &Path) -> Result<Vec<String>> {
    let mut pairs = Vec::new();
    for b in read_parquet(path)? {
        let idx = int_column(&b, path, "task_index")?;
        // LeRobot writes the task as the pandas index: a column named `task` (or, for an
        // unnamed index, `__index_level_0__`).
        let col = b
            .column_by_name("task")
            .or_else(|| b.column_by_name("__index_level_0__"))
            .ok_or_else(|| Error::MissingColumn {
                path: path.into(),
                column: "task".into(),
            })?;
        let s = match col.data_type() {
            DataType::Utf8 => col
                .as_string::<i32>()
                .iter()
                .map(|s| s.unwrap_or_default().to_string())
                .collect::<Vec<_>>(),
            DataType::LargeUtf8 => col
                .as_string::<i64>()
                .iter()
                .map(|s| s.unwrap_or_default().to_string())
                .collect(),
            t => return Err(type_error(path, "task", "string", t)),
        };
        pairs.extend(idx.into_iter().zip(s));
    }
    pairs.sort_by_key(|p| p.0);
    Ok(pairs.into_iter().map(|p| p.1).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ballplate::{BallPlate, BallPlateConfig};
    use crate::expert::{LqrConfig, LqrExpert};

    fn tmpdir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("pir2-sim-test-{}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        d
    }

    fn setup() -> (BallPlate, LqrExpert) {
        let cfg = BallPlateConfig::default();
        (
            BallPlate::new(cfg.clone()).unwrap(),
            LqrExpert::new(&cfg, LqrConfig::default()).unwrap(),
        )
    }

    fn short(n: usize) -> CollectConfig {
        CollectConfig {
            episodes: n,
            seed: 7,
            ..Default::default()
        }
    }

    #[test]
    fn template_formatting() {
        assert_eq!(
            fill_template(DATA_PATH, 0, 7),
            "data/chunk-000/file-007.parquet"
        );
        assert_eq!(
            fill_template("x/{chunk_index}/{file_index:05d}/{other}", 12, 3),
            "x/12/00003/{other}"
        );
    }

    #[test]
    fn collects_successful_demos_with_clean_labels() {
        let (mut env, mut ex) = setup();
        let mut calls = 0;
        let eps = collect_episodes(&mut env, &mut ex, &short(3), &mut |p| {
            calls += 1;
            assert!(p.kept <= 3);
        })
        .unwrap();
        assert_eq!(eps.len(), 3);
        assert!(calls >= 4);
        for e in &eps {
            assert!(e.success && e.done);
            assert_eq!(e.len(), 500);
            assert_eq!((e.fast_dim, e.slow_dim, e.action_dim), (6, 4, 2));
            // Labels are the expert's clamped actions.
            assert!(e.action.iter().all(|a| a.abs() <= 0.15 + 1e-6));
        }
        // Executed actions carry noise: "θ − last target" differs from the label's effect, so
        // re-running the episode without noise gives other observations.
        let e0 = &eps[0];
        let clean = run_episode(&mut env, &mut ex, e0.seed, 0.0, 0);
        assert_eq!(
            clean.fast(0),
            e0.fast(0),
            "same seed, same first observation"
        );
        assert_ne!(
            clean.fast, e0.fast,
            "action noise must change the trajectory"
        );
        let again = run_episode(&mut env, &mut ex, e0.seed, 0.01, 0);
        assert_eq!(&again, e0, "collection is deterministic");
    }

    #[test]
    fn write_read_roundtrip() {
        let root = tmpdir("roundtrip");
        let (mut env, mut ex) = setup();
        let spec = DatasetSpec::ballplate(50);
        let (stats, summary) = collect_to_dataset(
            &mut env,
            &mut ex,
            &short(3),
            &root,
            &spec,
            WriteMode::New,
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(stats.kept, 3);
        assert_eq!(summary.total_episodes, 3);
        assert!(root.join("data/chunk-000/file-000.parquet").exists());
        assert!(root
            .join("meta/episodes/chunk-000/file-000.parquet")
            .exists());
        assert!(root.join("meta/tasks.parquet").exists());
        let ds = read_dataset(&root).unwrap();
        assert_eq!(ds.fps, 50.0);
        assert_eq!(ds.tasks, spec.tasks);
        assert_eq!(ds.episodes.len(), 3);
        assert_eq!(ds.total_frames(), summary.total_frames);
        let mut env2 = env.clone();
        let direct = collect_episodes(&mut env2, &mut ex, &short(3), &mut |_| {}).unwrap();
        assert_eq!(ds.episodes, direct, "parquet round trip must be lossless");

        let info: Value =
            serde_json::from_str(&fs::read_to_string(root.join(INFO_PATH)).unwrap()).unwrap();
        assert_eq!(info["codebase_version"], "v3.0");
        assert_eq!(info["total_frames"], 1500);
        assert_eq!(info["features"]["observation.state"]["shape"], json!([6]));
        assert_eq!(
            info["features"]["observation.environment_state"]["names"],
            json!(["ball_x", "ball_y", "ball_vx", "ball_vy"])
        );
        assert_eq!(info["splits"]["train"], "0:3");
        let eb = read_parquet(&root.join("meta/episodes/chunk-000/file-000.parquet")).unwrap();
        let col = eb[0]
            .column_by_name("stats/index/max")
            .expect("per-episode index stats");
        let maxes = col.as_list::<i32>().value(2);
        assert_eq!(
            maxes.as_primitive::<Float64Type>().values().to_vec(),
            vec![1499.0]
        );
        assert!(eb[0]
            .column_by_name("stats/observation.state/q99")
            .is_some());
        let st: Value =
            serde_json::from_str(&fs::read_to_string(root.join(STATS_PATH)).unwrap()).unwrap();
        assert_eq!(st["action"]["count"], json!([1500]));
        assert_eq!(st["index"]["max"], json!([1499.0]));
        let m = st["observation.environment_state"]["mean"][0]
            .as_f64()
            .unwrap();
        let direct_mean = direct
            .iter()
            .flat_map(|e| (0..e.len()).map(move |t| e.slow(t)[0] as f64))
            .sum::<f64>()
            / 1500.0;
        assert!((m - direct_mean).abs() < 1e-9);
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn refuses_to_overwrite_and_resumes() {
        let root = tmpdir("resume");
        let (mut env, mut ex) = setup();
        let spec = DatasetSpec::ballplate(50);
        collect_to_dataset(
            &mut env,
            &mut ex,
            &short(2),
            &root,
            &spec,
            WriteMode::New,
            &mut |_| {},
        )
        .unwrap();
        let err = collect_to_dataset(
            &mut env,
            &mut ex,
            &short(3),
            &root,
            &spec,
            WriteMode::New,
            &mut |_| {},
        )
        .unwrap_err();
        assert!(matches!(err, Error::AlreadyExists { .. }), "{err}");
        assert!(err.to_string().contains("Resume"));
        // Resume to 3: only one more episode, in a new file pair.
        let mut seen = Vec::new();
        let (stats, summary) = collect_to_dataset(
            &mut env,
            &mut ex,
            &short(3),
            &root,
            &spec,
            WriteMode::Resume,
            &mut |p| seen.push(p.kept),
        )
        .unwrap();
        assert_eq!(stats.kept, 1);
        assert_eq!(seen.first(), Some(&2));
        assert_eq!(summary.total_episodes, 3);
        assert!(root.join("data/chunk-000/file-001.parquet").exists());
        assert!(root
            .join("meta/episodes/chunk-000/file-001.parquet")
            .exists());
        // Same episodes as a one-shot collection (the attempt sequence continues).
        let ds = read_dataset(&root).unwrap();
        let direct = collect_episodes(&mut env, &mut ex, &short(3), &mut |_| {}).unwrap();
        assert_eq!(ds.episodes, direct);
        // Resuming a complete dataset writes nothing new.
        let (stats, _) = collect_to_dataset(
            &mut env,
            &mut ex,
            &short(3),
            &root,
            &spec,
            WriteMode::Resume,
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(stats.kept, 0);
        assert!(!root.join("data/chunk-000/file-002.parquet").exists());
        // Overwrite starts from scratch.
        let (_, summary) = collect_to_dataset(
            &mut env,
            &mut ex,
            &short(1),
            &root,
            &spec,
            WriteMode::Overwrite,
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(summary.total_episodes, 1);
        assert!(!root.join("data/chunk-000/file-001.parquet").exists());
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn resume_refuses_orphan_data_files() {
        let root = tmpdir("orphan");
        let (mut env, mut ex) = setup();
        let spec = DatasetSpec::ballplate(50);
        collect_to_dataset(
            &mut env,
            &mut ex,
            &short(1),
            &root,
            &spec,
            WriteMode::New,
            &mut |_| {},
        )
        .unwrap();
        // A data file whose episodes file never got written.
        fs::copy(
            root.join("data/chunk-000/file-000.parquet"),
            root.join("data/chunk-000/file-001.parquet"),
        )
        .unwrap();
        let err = DatasetWriter::open(&root, spec.clone(), WriteMode::Resume).unwrap_err();
        assert!(
            matches!(&err, Error::Inconsistent { path, .. } if path.ends_with("data/chunk-000/file-001.parquet")),
            "{err}"
        );
        fs::remove_file(root.join("data/chunk-000/file-001.parquet")).unwrap();
        // A temporary leftover is harmless and its number is not reused.
        fs::write(root.join("data/chunk-000/file-001.parquet.tmp"), b"partial").unwrap();
        let w = DatasetWriter::open(&root, spec, WriteMode::Resume).unwrap();
        assert_eq!(w.file_no, 2);
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn resume_refuses_other_features() {
        let root = tmpdir("features");
        let (mut env, mut ex) = setup();
        let spec = DatasetSpec::ballplate(50);
        collect_to_dataset(
            &mut env,
            &mut ex,
            &short(1),
            &root,
            &spec,
            WriteMode::New,
            &mut |_| {},
        )
        .unwrap();
        let other = DatasetSpec {
            fps: 25,
            ..spec.clone()
        };
        let err = DatasetWriter::open(&root, other, WriteMode::Resume).unwrap_err();
        assert!(matches!(err, Error::Inconsistent { .. }), "{err}");
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn refuses_non_dataset_directory() {
        let root = tmpdir("nondataset");
        fs::create_dir_all(&root).unwrap();
        fs::write(root.join("notes.txt"), "mine").unwrap();
        for mode in [WriteMode::New, WriteMode::Resume] {
            let err = DatasetWriter::open(&root, DatasetSpec::ballplate(50), mode).unwrap_err();
            assert!(matches!(err, Error::AlreadyExists { .. }), "{err}");
        }
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn missing_file_and_column_errors_name_them() {
        let root = tmpdir("errors");
        let err = read_dataset(&root).unwrap_err();
        assert!(
            matches!(&err, Error::MissingFile { path } if path.ends_with("meta/info.json")),
            "{err}"
        );
        let (mut env, mut ex) = setup();
        let spec = DatasetSpec::ballplate(50);
        collect_to_dataset(
            &mut env,
            &mut ex,
            &short(1),
            &root,
            &spec,
            WriteMode::New,
            &mut |_| {},
        )
        .unwrap();
        let opts = ReadOptions {
            action_key: "action.absent".into(),
            ..Default::default()
        };
        let err = read_dataset_with(&root, &opts).unwrap_err();
        match &err {
            Error::MissingColumn { path, column } => {
                assert_eq!(column, "action.absent");
                assert!(path.ends_with("data/chunk-000/file-000.parquet"));
            }
            e => panic!("unexpected {e}"),
        }
        assert!(
            err.to_string().contains("file-000.parquet")
                && err.to_string().contains("action.absent")
        );
        // A column of the wrong type.
        let opts = ReadOptions {
            action_key: "next.done".into(),
            ..Default::default()
        };
        let err = read_dataset_with(&root, &opts).unwrap_err();
        assert!(
            matches!(&err, Error::ColumnType { column, .. } if column == "next.done"),
            "{err}"
        );
        // A missing data file.
        fs::remove_file(root.join("data/chunk-000/file-000.parquet")).unwrap();
        let err = read_dataset(&root).unwrap_err();
        assert!(
            matches!(&err, Error::MissingFile { path } if path.ends_with("file-000.parquet")),
            "{err}"
        );
        fs::remove_dir_all(&root).unwrap();
    }

    /// A dataset laid out like LeRobot writes it through HF `datasets`/pandas: variable-size
    /// float64 lists, int32 indices, no pir2 columns, task as an unnamed pandas index.
    #[test]
    fn reads_foreign_layout() {
        let root = tmpdir("foreign");
        let data = root.join("data/chunk-000/file-000.parquet");
        let n = 5usize;
        let state = ListArray::from_iter_primitive::<Float64Type, _, _>(
            (0..n).map(|t| Some(vec![Some(t as f64), Some(-(t as f64))])),
        );
        let action = ListArray::from_iter_primitive::<Float64Type, _, _>(
            (0..n).map(|t| Some(vec![Some(0.5 * t as f64)])),
        );
        let batch = RecordBatch::try_from_iter(vec![
            ("observation.state", Arc::new(state) as ArrayRef),
            ("action", Arc::new(action) as ArrayRef),
            (
                "episode_index",
                Arc::new(arrow_array::Int32Array::from(vec![0, 0, 1, 1, 1])) as ArrayRef,
            ),
            (
                "frame_index",
                Arc::new(Int64Array::from(vec![0, 1, 0, 1, 2])) as ArrayRef,
            ),
            (
                "timestamp",
                Arc::new(Float32Array::from(vec![0.0, 0.1, 0.0, 0.1, 0.2])) as ArrayRef,
            ),
        ])
        .unwrap();
        write_batch_file(&data, &batch).unwrap();
        let eps = RecordBatch::try_from_iter(vec![
            (
                "episode_index",
                Arc::new(Int64Array::from(vec![0, 1])) as ArrayRef,
            ),
            ("length", Arc::new(Int64Array::from(vec![2, 3])) as ArrayRef),
            (
                "data/chunk_index",
                Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
            ),
            (
                "data/file_index",
                Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
            ),
        ])
        .unwrap();
        write_batch_file(&root.join("meta/episodes/chunk-000/file-000.parquet"), &eps).unwrap();
        let tasks = RecordBatch::try_from_iter(vec![
            (
                "task_index",
                Arc::new(Int64Array::from(vec![0])) as ArrayRef,
            ),
            (
                "__index_level_0__",
                Arc::new(StringArray::from(vec!["push the T"])) as ArrayRef,
            ),
        ])
        .unwrap();
        write_batch_file(&root.join(TASKS_PATH), &tasks).unwrap();
        write_json_file(
            &root.join(INFO_PATH),
            &json!({"codebase_version": "v3.0", "fps": 10, "data_path": DATA_PATH, "features": {}}),
        )
        .unwrap();
        let ds = read_dataset(&root).unwrap();
        assert_eq!(ds.tasks, vec!["push the T".to_string()]);
        assert_eq!(ds.episodes.len(), 2);
        let e1 = &ds.episodes[1];
        assert_eq!(
            (e1.fast_dim, e1.slow_dim, e1.action_dim, e1.len()),
            (2, 0, 1, 3)
        );
        assert_eq!(e1.fast(2), &[4.0, -4.0]);
        assert_eq!(e1.action(0), &[1.0]);
        // Length mismatch is reported against the data file.
        let bad = RecordBatch::try_from_iter(vec![
            (
                "episode_index",
                Arc::new(Int64Array::from(vec![0, 1])) as ArrayRef,
            ),
            ("length", Arc::new(Int64Array::from(vec![2, 4])) as ArrayRef),
            (
                "data/chunk_index",
                Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
            ),
            (
                "data/file_index",
                Arc::new(Int64Array::from(vec![0, 0])) as ArrayRef,
            ),
        ])
        .unwrap();
        write_batch_file(&root.join("meta/episodes/chunk-000/file-000.parquet"), &bad).unwrap();
        let err = read_dataset(&root).unwrap_err();
        assert!(
            matches!(&err, Error::Inconsistent { reason, .. } if reason.contains("3 frames")),
            "{err}"
        );
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn stats_match_numpy_conventions() {
        let s = FeatureStats::compute(&[1.0, 10.0, 2.0, 20.0, 3.0, 30.0, 4.0, 40.0], 2);
        assert_eq!(s.count, 4);
        assert_eq!(s.min, vec![1.0, 10.0]);
        assert_eq!(s.max, vec![4.0, 40.0]);
        assert_eq!(s.mean, vec![2.5, 25.0]);
        assert!((s.std[0] - 1.25f64.sqrt()).abs() < 1e-12, "population std");
        // numpy.quantile([1,2,3,4], 0.5) = 2.5, 0.1 → 1.3
        assert!((s.quantiles[2][0] - 2.5).abs() < 1e-12);
        assert!((s.quantiles[1][0] - 1.3).abs() < 1e-12);
    }

    #[test]
    fn rejects_misshapen_episodes() {
        let root = tmpdir("shape");
        let mut w = DatasetWriter::open(&root, DatasetSpec::ballplate(50), WriteMode::New).unwrap();
        let mut e = Episode::new(5, 2, 2);
        e.push(&[0.0; 5], &[0.0; 2], &[0.0; 2]);
        assert!(matches!(w.append(&e), Err(Error::EpisodeShape { .. })));
        assert!(matches!(
            w.append(&Episode::new(6, 2, 2)),
            Err(Error::EpisodeShape { .. })
        ));
        let _ = fs::remove_dir_all(&root);
    }
}
