//! Demonstrations: collection into in-memory [`Episode`]s, and LeRobotDataset v3.0
//! (state-only) writing and reading. Shared by every task of the crate.
//!
//! # In memory
//!
//! [`collect`] runs an [`Expert`] on an [`Environment`](pir2_runtime::Environment) and hands
//! each finished [`Episode`] (fast and slow observations, clean expert actions, row-major
//! `f32`) to a sink; the trainer can use [`collect_episodes`] and never touch parquet.
//! Actions are *executed* with Gaussian noise ([`CollectConfig::action_noise`]) while the
//! *labels* are the clean expert actions. The slow channel is stored undelayed; the trainer
//! applies `d_vis`.
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
//! `observation.environment_state` (slow), `action` (the three keys are
//! [`DatasetSpec::keys`], these by default), `timestamp` (`f32`, s), `frame_index`,
//! `episode_index`, `index` (global frame index), `task_index` (`i64`), `next.done`,
//! `next.success` (`bool`, true on the last frame of an episode that ended / succeeded).
//!
//! # Reading any state-only dataset
//!
//! [`read_dataset`] reads our three channels. [`read_selected`] reads any LeRobotDataset
//! v3.0 (LeRobot's own writer included) by feature name: the fast and slow observations are
//! the named `float32`/`float64` vector (or scalar) features concatenated in order, the
//! action one named feature; each is checked against `meta/info.json` first, and a missing
//! key, an image/video/integer feature or a width that does not match is one
//! [`Error::Feature`] or [`Error::ColumnType`] naming the key.
//!
//! # Camera videos
//!
//! [`VideoDataset`] reads the frame index of a dataset with video features (timestamps,
//! tasks, which file and where in it each episode lies) and [`FrameReader`] decodes the
//! frames, streaming, with the `ffmpeg` program (see the `video` module's docs for the
//! layout and the timestamp rule, LeRobot's). Image features (PNG/JPEG bytes in the data
//! files) are read and decoded in Rust by the same reader.
//!
//! Writing never replaces an existing dataset silently: [`WriteMode::New`] refuses a
//! non-empty directory, [`WriteMode::Resume`] appends episodes in new data/episode files
//! (one pair per writing session), [`WriteMode::Overwrite`] writes the new dataset into a
//! staging directory and swaps it for the old `data/` and `meta/` only when
//! [`DatasetWriter::finish`] has written at least one episode (until then the old dataset
//! stays readable). Files are written under a temporary name and renamed; `meta/info.json` is written
//! last, so an interrupted session leaves the previous dataset readable.

mod collect;
mod read;
mod select;
mod spec;
mod stats;
#[cfg(test)]
mod tests;
mod video;
mod write;

pub use collect::*;
pub use read::*;
pub use select::{check_selection, float_features, read_selected, FeatureSelection, FloatFeature};
pub use spec::*;
pub use stats::*;
pub use video::{
    check_ffmpeg, ffmpeg_program, DecodedFrame, FrameReader, VideoDataset, VideoEpisode, VideoSpan,
    VideoStream, DEFAULT_TOLERANCE_S, VIDEO_PATH,
};
pub use write::*;

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
/// Largest zero-padding width a path template may ask for (`{file_index:0Nd}`, N ≤ this).
pub const MAX_TEMPLATE_WIDTH: usize = 32;
/// Longest path template accepted from `meta/info.json`, in bytes.
pub const MAX_TEMPLATE_LEN: usize = 4096;
/// `meta/info.json`.
pub const INFO_PATH: &str = "meta/info.json";
/// Where a resumed session moves the data file of an interrupted write (outside `data/`, so
/// LeRobot's `data/*/*.parquet` does not load it), under the same relative path.
pub const INTERRUPTED_DIR: &str = ".pir2-interrupted";
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

    /// The episode with `frames` slow observations per frame, oldest first: frame `t` holds
    /// the slow observations of frames `t − frames + 1 ..= t`, the first frame repeated
    /// before the episode start (as the fast history is padded). This is what
    /// [`pir2_runtime::io::SlowFrames`] produces at deployment from one frame per tick, so a
    /// policy trained on it sees the same layout, delays included (a slow input `d` ticks
    /// old is frames `t − d − frames + 1 ..= t − d`). `frames = 1` returns a copy.
    ///
    /// # Panics
    /// If `frames` is 0.
    pub fn with_slow_frames(&self, frames: usize) -> Episode {
        assert!(frames >= 1, "at least one slow frame");
        let s = self.slow_dim;
        let mut slow = Vec::with_capacity(self.len() * s * frames);
        for t in 0..self.len() {
            for j in 0..frames {
                let tt = (t + j + 1).saturating_sub(frames);
                slow.extend_from_slice(&self.slow[tt * s..(tt + 1) * s]);
            }
        }
        Episode {
            slow,
            slow_dim: s * frames,
            ..self.clone()
        }
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
