//! What a dataset holds: feature names, fps, tasks, and how a writing session opens.

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::PathBuf;

use super::*;

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
    /// Feature keys of the three channels (default: `observation.state`,
    /// `observation.environment_state`, `action`).
    #[serde(default)]
    pub keys: FeatureKeys,
}

/// The feature keys a dataset stores its fast, slow and action channels under.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FeatureKeys {
    /// Fast observation.
    pub fast: String,
    /// Slow observation.
    pub slow: String,
    /// Action.
    pub action: String,
}

impl Default for FeatureKeys {
    fn default() -> Self {
        Self {
            fast: KEY_FAST.into(),
            slow: KEY_SLOW.into(),
            action: KEY_ACTION.into(),
        }
    }
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
            keys: FeatureKeys::default(),
        }
    }

    /// The `features` object of `info.json`, in column order.
    pub fn features_json(&self) -> Value {
        let mut f = serde_json::Map::new();
        let vec_ft =
            |names: &[String]| json!({"dtype": "float32", "shape": [names.len()], "names": names});
        f.insert(self.keys.fast.clone(), vec_ft(&self.fast_names));
        if !self.slow_names.is_empty() {
            f.insert(self.keys.slow.clone(), vec_ft(&self.slow_names));
        }
        f.insert(self.keys.action.clone(), vec_ft(&self.action_names));
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
pub(super) const SCALAR_COLUMNS: [(&str, &str); 7] = [
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
    /// Replace `data/` and `meta/` of an existing dataset: the new dataset is written into a
    /// staging directory and swapped in when the session finishes with at least one episode.
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
    /// Data files of an interrupted write that a resumed session moved aside (see
    /// [`crate::dataset::DatasetWriter::open`]), where they are now.
    pub set_aside: Vec<PathBuf>,
}
