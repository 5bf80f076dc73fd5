//! Per-feature statistics (`meta/stats.json` and the episodes' `stats/*` columns).

use crate::error::{Error, Result};
use arrow_array::builder::{ListBuilder, StringBuilder};
use arrow_array::types::{Float64Type, Int64Type};
use arrow_array::{ArrayRef, BooleanArray, Int64Array, ListArray, RecordBatch, UInt64Array};
use arrow_schema::{DataType, Field, Schema};
use serde_json::{json, Value};
use std::path::Path;
use std::sync::Arc;

use arrow_array::Array;

use super::*;

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
pub(super) fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
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
pub(super) fn feature_columns<'a>(
    eps: impl Iterator<Item = &'a Episode> + Clone,
    spec: &'a DatasetSpec,
) -> Vec<(&'a str, Vec<f64>, usize)> {
    let mut out = Vec::new();
    let widen = |v: &[f32]| v.iter().map(|x| *x as f64).collect::<Vec<_>>();
    out.push((
        spec.keys.fast.as_str(),
        eps.clone().flat_map(|e| widen(&e.fast)).collect(),
        spec.fast_names.len(),
    ));
    if !spec.slow_names.is_empty() {
        out.push((
            spec.keys.slow.as_str(),
            eps.clone().flat_map(|e| widen(&e.slow)).collect(),
            spec.slow_names.len(),
        ));
    }
    out.push((
        spec.keys.action.as_str(),
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

pub(super) fn dataset_stats(eps: &[LoadedEpisode], spec: &DatasetSpec) -> Value {
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

pub(super) fn list_f64_array(rows: Vec<Vec<f64>>) -> ArrayRef {
    Arc::new(ListArray::from_iter_primitive::<Float64Type, _, _>(
        rows.into_iter().map(|r| Some(r.into_iter().map(Some))),
    ))
}

pub(super) fn episodes_batch(
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
    let per_ep: Vec<Vec<(&str, FeatureStats)>> = eps
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
