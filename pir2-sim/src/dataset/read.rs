//! The LeRobotDataset v3.0 reader.
//!
//! One file on purpose: parquet reading, column typing and the LeRobot metadata checks work on
//! the same column descriptions (`Columns`).

use crate::error::{Error, Result};
use arrow_array::types::{Float32Type, Float64Type, Int32Type, Int64Type, UInt64Type};
use arrow_array::{ArrayRef, RecordBatch};
use arrow_schema::DataType;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ProjectionMask;
use serde_json::Value;
use std::collections::BTreeMap;
use std::fs::{self, File};
use std::path::Path;

use arrow_array::cast::AsArray;
use arrow_array::Array;

use super::*;

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
pub(super) struct LoadedEpisode {
    pub(super) episode_index: i64,
    pub(super) from: i64,
    pub(super) episode: Episode,
}

pub(super) fn read_info(root: &Path) -> Result<Value> {
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

/// Check a path template of `meta/info.json` before any path is built from it: relative, no
/// `..` segment, at most [`MAX_TEMPLATE_LEN`] bytes, and every `{name}` / `{name:0Nd}`
/// placeholder one of `names` with a width of at most [`MAX_TEMPLATE_WIDTH`].
pub(super) fn check_template(
    info_path: &Path,
    field: &str,
    template: &str,
    names: &[&str],
) -> Result<()> {
    let bad = |reason: String| {
        Err(Error::PathTemplate {
            path: info_path.into(),
            field: field.into(),
            template: template.chars().take(200).collect(),
            reason,
        })
    };
    if template.is_empty() {
        return bad("it is empty".into());
    }
    if template.len() > MAX_TEMPLATE_LEN {
        return bad(format!(
            "it is {} bytes long (at most {MAX_TEMPLATE_LEN})",
            template.len()
        ));
    }
    if template.contains('\0') {
        return bad("it contains a NUL byte".into());
    }
    if template.starts_with(['/', '\\']) || Path::new(template).has_root() {
        return bad("it is absolute; it must be relative to the dataset root".into());
    }
    if template.split(['/', '\\']).any(|seg| seg == "..") {
        return bad("a `..` segment leaves the dataset root".into());
    }
    let mut rest = template;
    while let Some(open) = rest.find(['{', '}']) {
        if rest[open..].starts_with('}') {
            return bad("unmatched `}`".into());
        }
        let Some(close) = rest[open + 1..].find(['{', '}']) else {
            return bad("unclosed `{`".into());
        };
        let close = open + 1 + close;
        if rest[close..].starts_with('{') {
            return bad("nested `{`".into());
        }
        let inner = &rest[open + 1..close];
        let (name, fmt) = inner.split_once(':').unwrap_or((inner, ""));
        if !names.contains(&name) {
            return bad(format!(
                "unknown placeholder `{{{name}}}` (known: {})",
                names.join(", ")
            ));
        }
        if !fmt.is_empty() {
            let width = fmt
                .strip_suffix('d')
                .filter(|w| !w.is_empty() && w.bytes().all(|b| b.is_ascii_digit()))
                .map(|w| w.trim_start_matches('0'));
            match width {
                None => {
                    return bad(format!(
                        "placeholder `{{{inner}}}`: format must be `0Nd` (zero-padded decimal)"
                    ))
                }
                Some(w) if w.len() > 3 || w.parse::<usize>().unwrap_or(0) > MAX_TEMPLATE_WIDTH => {
                    return bad(format!(
                        "placeholder `{{{inner}}}`: width above {MAX_TEMPLATE_WIDTH}"
                    ))
                }
                Some(_) => {}
            }
        }
        rest = &rest[close + 1..];
    }
    Ok(())
}

pub(super) fn read_parquet(path: &Path) -> Result<Vec<RecordBatch>> {
    read_parquet_columns(path, None)
}

/// [`read_parquet`] keeping only the named top-level columns (those the file has; `None`:
/// all). A camera's image column holds every frame's encoded image, so readers of the
/// other columns leave it out.
pub(super) fn read_parquet_columns(path: &Path, keep: Option<&[&str]>) -> Result<Vec<RecordBatch>> {
    let file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(Error::MissingFile { path: path.into() })
        }
        Err(e) => return Err(Error::io(path, e)),
    };
    // The parquet and arrow crates still panic on some malformed inputs (e.g. an embedded
    // arrow schema with an impossible integer width): a bad file must be an error naming
    // it, so the decoding runs behind `catch_unwind` (the panic hook still prints the
    // decoder's message).
    let decode = || -> Result<Vec<RecordBatch>> {
        let mut builder =
            ParquetRecordBatchReaderBuilder::try_new(file).map_err(|e| Error::parquet(path, e))?;
        if let Some(keep) = keep {
            let roots: Vec<usize> = builder
                .schema()
                .fields()
                .iter()
                .enumerate()
                .filter(|(_, f)| keep.contains(&f.name().as_str()))
                .map(|(i, _)| i)
                .collect();
            let mask = ProjectionMask::roots(builder.parquet_schema(), roots);
            builder = builder.with_projection(mask);
        }
        let reader = builder.build().map_err(|e| Error::parquet(path, e))?;
        reader
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|source| Error::Arrow {
                path: path.into(),
                source,
            })
    };
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(decode)).unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "panic without a message".into());
        Err(Error::Malformed {
            path: path.into(),
            message,
        })
    })
}

pub(super) fn column<'a>(batch: &'a RecordBatch, path: &Path, name: &str) -> Result<&'a ArrayRef> {
    batch
        .column_by_name(name)
        .ok_or_else(|| Error::MissingColumn {
            path: path.into(),
            column: name.into(),
        })
}

pub(super) fn type_error(path: &Path, name: &str, expected: &str, found: &DataType) -> Error {
    Error::ColumnType {
        path: path.into(),
        column: name.into(),
        expected: expected.into(),
        found: found.to_string(),
    }
}

/// An integer column as `i64` (accepts int32/int64/uint64).
pub(super) fn int_column(batch: &RecordBatch, path: &Path, name: &str) -> Result<Vec<i64>> {
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
pub(super) fn vec_column(
    batch: &RecordBatch,
    path: &Path,
    name: &str,
) -> Result<(Vec<f32>, usize)> {
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

pub(super) fn bool_column(
    batch: &RecordBatch,
    path: &Path,
    name: &str,
) -> Result<Option<Vec<bool>>> {
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

/// Bound on global frame indices read from `meta/episodes` (2^48 frames).
const MAX_GLOBAL_INDEX: i64 = 1 << 48;

pub(super) fn read_episode_rows(root: &Path) -> Result<Vec<EpisodeRow>> {
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
    let mut acc: i64 = 0;
    for r in &mut rows {
        let bad = |column: &str, value: i64| Error::Inconsistent {
            path: dir.clone(),
            reason: format!(
                "episode {}: `{column}` is {value}; it must be in 0..{}",
                r.episode_index,
                i64::from(u32::MAX)
            ),
        };
        for (column, value) in [
            ("episode_index", r.episode_index),
            ("length", r.length),
            ("data/chunk_index", r.data_chunk),
            ("data/file_index", r.data_file),
        ] {
            if !(0..i64::from(u32::MAX)).contains(&value) {
                return Err(bad(column, value));
            }
        }
        if r.from < 0 || r.to < 0 {
            r.from = acc;
            r.to = acc.saturating_add(r.length);
        }
        if r.from > r.to || r.to >= MAX_GLOBAL_INDEX {
            return Err(Error::Inconsistent {
                path: dir.clone(),
                reason: format!(
                    "episode {}: dataset_from_index {} .. dataset_to_index {} is not a range within 0..{MAX_GLOBAL_INDEX}",
                    r.episode_index, r.from, r.to
                ),
            });
        }
        acc = r.to;
    }
    Ok(rows)
}

/// Read the frames of the given episodes (grouped by their data files).
pub(super) fn read_frames(
    root: &Path,
    rows: &[EpisodeRow],
    keys: &FeatureKeys,
) -> Result<Vec<LoadedEpisode>> {
    let opts = ReadOptions {
        fast_key: keys.fast.clone(),
        slow_key: keys.slow.clone(),
        action_key: keys.action.clone(),
    };
    read_frames_with(root, DATA_PATH, rows, &Columns::of(&opts))
}

pub(super) fn read_frames_with(
    root: &Path,
    data_tmpl: &str,
    rows: &[EpisodeRow],
    cols: &Columns,
) -> Result<Vec<LoadedEpisode>> {
    let mut files: BTreeMap<(i64, i64), ()> = BTreeMap::new();
    for r in rows {
        files.insert((r.data_chunk, r.data_file), ());
    }
    let mut by_ep: BTreeMap<i64, (Episode, Vec<i64>)> = BTreeMap::new();
    // Widths of the fast / slow / action columns, fixed by the first rows read: every row
    // group of every file must agree (one error naming the column otherwise).
    let mut widths: [Option<usize>; 3] = [None; 3];
    for &(chunk, file) in files.keys() {
        let path = root.join(fill_template(data_tmpl, chunk as usize, file as usize));
        for b in read_parquet(&path)? {
            let [(fk, fname), (sk, sname), (ak, aname)] = cols.groups();
            let (fast, fd) = cols.read_group(&b, &path, fk, false)?;
            let (slow, sd) = cols.read_group(&b, &path, sk, cols.slow_optional)?;
            let (action, ad) = cols.read_group(&b, &path, ak, false)?;
            for (seen, (name, w)) in
                widths
                    .iter_mut()
                    .zip([(&fname, fd), (&sname, sd), (&aname, ad)])
            {
                match *seen {
                    None => *seen = Some(w),
                    Some(first) if first != w => {
                        return Err(Error::ColumnType {
                            path: path.clone(),
                            column: name.to_string(),
                            expected: format!("rows of width {first} (as the rows read before)"),
                            found: format!("rows of width {w}"),
                        })
                    }
                    Some(_) => {}
                }
            }
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
    read_dataset_columns(root, &Columns::of(opts))
}

/// `meta/info.json` of the dataset at `root`, checked: a v3.x codebase version, a positive
/// `fps`, usable path templates. Returns it with the fps and the data path template.
pub(super) fn read_info_checked(root: &Path) -> Result<(Value, f64, String)> {
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
    if !(fps.is_finite() && fps > 0.0) {
        return Err(Error::Inconsistent {
            path: info_path,
            reason: format!("`fps` is {fps}; it must be positive"),
        });
    }
    let template = |field: &str, names: &[&str]| -> Result<Option<String>> {
        match info.get(field) {
            None | Some(Value::Null) => Ok(None),
            Some(Value::String(t)) => {
                check_template(&info_path, field, t, names)?;
                Ok(Some(t.clone()))
            }
            Some(v) => Err(Error::PathTemplate {
                path: info_path.clone(),
                field: field.into(),
                template: v.to_string().chars().take(200).collect(),
                reason: "not a string".into(),
            }),
        }
    };
    let data_tmpl =
        template("data_path", &["chunk_index", "file_index"])?.unwrap_or(DATA_PATH.into());
    // State-only reader: videos are not read, but a bad template is still refused.
    template("video_path", &["video_key", "chunk_index", "file_index"])?;
    Ok((info, fps, data_tmpl))
}

/// Read the dataset at `root` with the given column groups.
pub(super) fn read_dataset_columns(root: &Path, cols: &Columns) -> Result<Dataset> {
    let (info, fps, data_tmpl) = read_info_checked(root)?;
    let rows = read_episode_rows(root)?;
    let mut loaded = read_frames_with(root, &data_tmpl, &rows, cols)?;
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

pub(super) fn fill_flags_from_frames(
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

pub(super) fn read_tasks(path: &Path) -> Result<Vec<String>> {
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

/// Column groups to read: each channel is its keys' columns concatenated per frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Columns {
    pub(super) fast: Vec<String>,
    pub(super) slow: Vec<String>,
    pub(super) action: Vec<String>,
    /// A slow group missing from a data file means "no slow channel" (our own layout, where
    /// `observation.environment_state` is optional) instead of an error.
    pub(super) slow_optional: bool,
    /// Width each key must have (from `info.json`), when known.
    pub(super) widths: Vec<(String, usize)>,
}

impl Columns {
    /// The columns of [`ReadOptions`] (one key per channel, the slow one optional).
    pub(super) fn of(opts: &ReadOptions) -> Self {
        Columns {
            fast: vec![opts.fast_key.clone()],
            slow: vec![opts.slow_key.clone()],
            action: vec![opts.action_key.clone()],
            slow_optional: true,
            widths: Vec::new(),
        }
    }

    /// The three groups with their display names (keys joined by `+`).
    pub(super) fn groups(&self) -> [(&[String], String); 3] {
        [
            (&self.fast[..], self.fast.join("+")),
            (&self.slow[..], self.slow.join("+")),
            (&self.action[..], self.action.join("+")),
        ]
    }

    /// Read one group of `batch`: its keys' columns concatenated per row, and the total width.
    /// An optional slow group absent from the file reads as width 0.
    pub(super) fn read_group(
        &self,
        batch: &RecordBatch,
        path: &Path,
        keys: &[String],
        optional: bool,
    ) -> Result<(Vec<f32>, usize)> {
        if keys.is_empty() || (optional && keys.iter().any(|k| batch.column_by_name(k).is_none())) {
            return Ok((Vec::new(), 0));
        }
        let n = batch.num_rows();
        let mut parts = Vec::with_capacity(keys.len());
        for k in keys {
            let (values, w) = vec_column(batch, path, k)?;
            if let Some((_, want)) = self.widths.iter().find(|(key, _)| key == k) {
                if w != *want {
                    return Err(Error::ColumnType {
                        path: path.into(),
                        column: k.clone(),
                        expected: format!("rows of width {want} (its shape in meta/info.json)"),
                        found: format!("rows of width {w}"),
                    });
                }
            }
            parts.push((values, w));
        }
        let width: usize = parts.iter().map(|p| p.1).sum();
        if parts.len() == 1 {
            return Ok(parts.pop().map(|p| (p.0, width)).unwrap_or_default());
        }
        let mut out = Vec::with_capacity(n * width);
        for i in 0..n {
            for (values, w) in &parts {
                out.extend_from_slice(&values[i * w..(i + 1) * w]);
            }
        }
        Ok((out, width))
    }
}
