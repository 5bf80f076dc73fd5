//! Reading chosen float features of any state-only LeRobotDataset v3.0 by name.
//!
//! A training task names which `meta/info.json` features make its channels: the fast
//! observation is the concatenation of one or more float features in the order given, the
//! slow observation likewise (or none), the action one feature. Each must be declared in
//! `info.json` with dtype `float32` or `float64` and a one-dimensional shape `[n]` (a scalar
//! is `[1]`); the data files must hold it as a fixed-size or same-width list of floats, or a
//! plain float column for a scalar. Anything else (a missing key, an image or video feature,
//! an integer, bool or string column, a matrix, a width that differs from `info.json`) is one
//! [`Error::Feature`] or [`Error::ColumnType`] naming the key.

use serde_json::Value;
use std::path::Path;

use super::read::{read_info_checked, Columns};
use super::*;

/// Which features of a dataset make the fast observation, the slow observation and the action.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FeatureSelection {
    /// Fast observation: these features concatenated in order (at least one).
    pub fast: Vec<String>,
    /// Slow observation: these features concatenated in order (empty: no slow channel).
    pub slow: Vec<String>,
    /// The action feature.
    pub action: String,
}

/// A float vector feature of `meta/info.json`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FloatFeature {
    /// Feature key.
    pub key: String,
    /// `float32` or `float64`.
    pub dtype: String,
    /// Width (`shape[0]`).
    pub width: usize,
}

/// The float vector features `info` declares (dtype `float32`/`float64`, shape `[n]`),
/// sorted by key.
pub fn float_features(info: &Value) -> Vec<FloatFeature> {
    let Some(features) = info.get("features").and_then(Value::as_object) else {
        return Vec::new();
    };
    features
        .iter()
        .filter_map(|(key, f)| {
            let dtype = f.get("dtype").and_then(Value::as_str)?;
            if dtype != "float32" && dtype != "float64" {
                return None;
            }
            let width = one_dim(f.get("shape"))?;
            Some(FloatFeature {
                key: key.clone(),
                dtype: dtype.into(),
                width,
            })
        })
        .collect()
}

/// `[n]` with `1 ≤ n ≤ 2^16` → `n`.
fn one_dim(shape: Option<&Value>) -> Option<usize> {
    match shape?.as_array()?.as_slice() {
        [n] => n
            .as_u64()
            .filter(|n| (1..=1 << 16).contains(n))
            .map(|n| n as usize),
        _ => None,
    }
}

/// Check `sel` against `meta/info.json` of the dataset at `root`; returns the width of each
/// selected key.
pub fn check_selection(root: &Path, sel: &FeatureSelection) -> Result<Vec<FloatFeature>> {
    let (info, _, _) = read_info_checked(root)?;
    check_selection_in(&root.join(INFO_PATH), &info, sel)
}

fn check_selection_in(
    info_path: &Path,
    info: &Value,
    sel: &FeatureSelection,
) -> Result<Vec<FloatFeature>> {
    let err = |key: &str, reason: String| Error::Feature {
        path: info_path.into(),
        key: key.into(),
        reason,
    };
    let features = info
        .get("features")
        .and_then(Value::as_object)
        .ok_or_else(|| Error::Inconsistent {
            path: info_path.into(),
            reason: "no `features` object".into(),
        })?;
    if sel.fast.is_empty() {
        return Err(Error::ConfigValue {
            field: "fast keys",
            reason: "at least one feature key is needed".into(),
        });
    }
    let available = || {
        let f: Vec<String> = float_features(info).into_iter().map(|f| f.key).collect();
        if f.is_empty() {
            "the dataset declares no float vector features".to_string()
        } else {
            format!("float features there: {}", f.join(", "))
        }
    };
    let mut out: Vec<FloatFeature> = Vec::new();
    for key in sel.fast.iter().chain(&sel.slow).chain([&sel.action]) {
        if out.iter().any(|f| &f.key == key) {
            return Err(err(key, "is selected more than once".into()));
        }
        let Some(f) = features.get(key) else {
            return Err(err(
                key,
                format!("is not in meta/info.json `features` ({})", available()),
            ));
        };
        let dtype = f.get("dtype").and_then(Value::as_str).unwrap_or("");
        match dtype {
            "float32" | "float64" => {}
            "video" | "image" => {
                return Err(err(
                    key,
                    format!(
                        "is a {dtype} feature; training reads state-only float features \
                         (float32/float64 vectors)"
                    ),
                ))
            }
            _ => {
                return Err(err(
                    key,
                    format!("has dtype {dtype:?}; only float32/float64 features can be read"),
                ))
            }
        }
        let Some(width) = one_dim(f.get("shape")) else {
            let shape = f.get("shape").map(Value::to_string).unwrap_or_default();
            return Err(err(
                key,
                format!(
                    "has shape {shape}; only fixed-width vectors [n] (a scalar is [1], \
                     n ≤ 65536) can be read"
                ),
            ));
        };
        out.push(FloatFeature {
            key: key.clone(),
            dtype: dtype.into(),
            width,
        });
    }
    Ok(out)
}

/// Read the features `sel` names from the LeRobotDataset v3.0 at `root` into memory: each
/// episode's fast, slow and action rows are the selected features concatenated in order
/// (`f32`; `float64` values are rounded). `episode_index`, `frame_index` and the
/// `meta/episodes` table are required, as for [`read_dataset`].
pub fn read_selected(root: &Path, sel: &FeatureSelection) -> Result<Dataset> {
    let (info, _, _) = read_info_checked(root)?;
    let widths = check_selection_in(&root.join(INFO_PATH), &info, sel)?;
    let cols = Columns {
        fast: sel.fast.clone(),
        slow: sel.slow.clone(),
        action: vec![sel.action.clone()],
        slow_optional: false,
        widths: widths.into_iter().map(|f| (f.key, f.width)).collect(),
    };
    super::read::read_dataset_columns(root, &cols)
}
