//! The LeRobotDataset v3.0 writer (parquet frames, episode metadata, info, tasks).

use crate::error::{Error, Result};
use arrow_array::{
    ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, Int64Array, RecordBatch, StringArray,
};
use arrow_schema::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;
use serde_json::{json, Value};
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::*;

pub(super) fn fill_template(template: &str, chunk: usize, file: usize) -> String {
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
                    .unwrap_or(0)
                    .min(MAX_TEMPLATE_WIDTH);
                out.push_str(&format!("{v:0width$}"));
            }
            None => out.push_str(&rest[open..open + close + 1]),
        }
        rest = &rest[open + close + 1..];
    }
    out.push_str(rest);
    out
}

pub(super) fn chunk_file(n: usize) -> (usize, usize) {
    (n / CHUNKS_SIZE, n % CHUNKS_SIZE)
}

pub(super) fn write_props() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .build()
}

pub(super) fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

pub(super) fn create_parent(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    Ok(())
}

pub(super) fn rename(from: &Path, to: &Path) -> Result<()> {
    fs::rename(from, to).map_err(|e| Error::io(to, e))
}

pub(super) fn write_batch_file(path: &Path, batch: &RecordBatch) -> Result<()> {
    create_parent(path)?;
    let tmp = tmp_path(path);
    let file = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let mut w = ArrowWriter::try_new(file, batch.schema(), Some(write_props()))
        .map_err(|e| Error::parquet(path, e))?;
    w.write(batch).map_err(|e| Error::parquet(path, e))?;
    w.close().map_err(|e| Error::parquet(path, e))?;
    rename(&tmp, path)
}

pub(super) fn write_json_file(path: &Path, value: &Value) -> Result<()> {
    create_parent(path)?;
    let tmp = tmp_path(path);
    let text = serde_json::to_string_pretty(value).map_err(|e| Error::json(path, e))?;
    fs::write(&tmp, text + "\n").map_err(|e| Error::io(&tmp, e))?;
    rename(&tmp, path)
}

pub(super) fn f32_list_field(name: &str, width: usize) -> Field {
    Field::new(
        name,
        DataType::FixedSizeList(
            Arc::new(Field::new_list_field(DataType::Float32, true)),
            width as i32,
        ),
        true,
    )
}

pub(super) fn f32_list_array(values: Vec<f32>, width: usize, path: &Path) -> Result<ArrayRef> {
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
pub(super) struct EpisodeRow {
    pub(super) episode_index: i64,
    pub(super) tasks: Vec<String>,
    pub(super) length: i64,
    pub(super) data_chunk: i64,
    pub(super) data_file: i64,
    pub(super) from: i64,
    pub(super) to: i64,
    pub(super) meta_chunk: i64,
    pub(super) meta_file: i64,
    pub(super) seed: u64,
    pub(super) success: bool,
    pub(super) attempt: u64,
}

/// Frames buffered for the current data file.
#[derive(Debug, Default)]
pub(super) struct FrameBuffer {
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
/// per flush. Episodes are buffered in memory until [`DatasetWriter::flush`] or
/// [`DatasetWriter::finish`] writes them; after a flush the dataset on disk is complete and
/// readable (a killed process loses only the episodes appended since), and a
/// [`WriteMode::Resume`] session continues it.
#[derive(Debug)]
pub struct DatasetWriter {
    pub(super) root: PathBuf,
    pub(super) spec: DatasetSpec,
    pub(super) existing: Vec<EpisodeRow>,
    pub(super) new_rows: Vec<EpisodeRow>,
    pub(super) frames: FrameBuffer,
    pub(super) file_no: usize,
    pub(super) total_frames: i64,
    pub(super) next_attempt: u64,
    /// [`WriteMode::Overwrite`] of an existing dataset: the dataset root to replace.
    /// `root` is then a staging directory inside it, swapped in by [`DatasetWriter::finish`]
    /// once at least one episode is written (and removed if the writer is dropped first).
    pub(super) replace: Option<PathBuf>,
    /// Episodes written by earlier flushes of this session.
    pub(super) flushed: usize,
    /// The data file of the last flush.
    pub(super) last_data_file: Option<PathBuf>,
    /// Data files of an interrupted write moved aside by [`DatasetWriter::open`].
    pub(super) set_aside: Vec<PathBuf>,
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
        let mut set_aside = Vec::new();
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
                let last = referenced.iter().next_back().copied();
                for n in file_numbers(&root.join("data"), true)? {
                    if !referenced.contains(&n) {
                        let (c, f) = chunk_file(n);
                        // The tail of a flush killed between its data file and its episodes
                        // file: its episodes are in no metadata (a seeded collection makes
                        // them again). Moved aside, out of LeRobot's `data/*/*.parquet`.
                        let rel = fill_template(DATA_PATH, c, f);
                        let interrupted = last.is_none_or(|l| n > l)
                            && !root.join(fill_template(EPISODES_PATH, c, f)).exists();
                        if interrupted {
                            let to = root.join(INTERRUPTED_DIR).join(&rel);
                            create_parent(&to)?;
                            rename(&root.join(&rel), &to)?;
                            set_aside.push(to);
                            continue;
                        }
                        return Err(Error::Inconsistent {
                            path: root.join(fill_template(DATA_PATH, c, f)),
                            reason: "data file not referenced by meta/episodes (left by an interrupted session?); \
                                     remove it, or rewrite the dataset with WriteMode::Overwrite"
                                .into(),
                        });
                    }
                }
            }
            _ => {}
        }
        // Overwrite of an existing directory: write the new dataset into a staging directory
        // inside it; the old `data/` and `meta/` stay until `finish` swaps them out.
        let (root, replace) = if mode == WriteMode::Overwrite && non_empty {
            let staging = root.join(unique_name(".pir2-overwrite"));
            fs::create_dir(&staging).map_err(|e| Error::io(&staging, e))?;
            (staging, Some(root.to_path_buf()))
        } else {
            (root.to_path_buf(), None)
        };
        let root = root.as_path();
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
            replace,
            flushed: 0,
            last_data_file: None,
            set_aside,
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

    /// Data files of an interrupted write that [`DatasetWriter::open`] moved aside (a
    /// [`WriteMode::Resume`] of a dataset whose last flush was killed before its metadata),
    /// where they are now.
    pub fn set_aside(&self) -> &[PathBuf] {
        &self.set_aside
    }

    /// Episodes appended since the last flush (what a killed process would lose).
    pub fn pending(&self) -> usize {
        self.new_rows.len()
    }

    /// Append one episode (buffered until [`DatasetWriter::flush`] or
    /// [`DatasetWriter::finish`]).
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
        let mut fields = vec![f32_list_field(&spec.keys.fast, spec.fast_names.len())];
        let mut cols = vec![f32_list_array(f.fast, spec.fast_names.len(), path)?];
        if !spec.slow_names.is_empty() {
            fields.push(f32_list_field(&spec.keys.slow, spec.slow_names.len()));
            cols.push(f32_list_array(f.slow, spec.slow_names.len(), path)?);
        }
        fields.push(f32_list_field(&spec.keys.action, spec.action_names.len()));
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

    /// Write the episodes appended since the last flush: one new data file and one new
    /// episodes file, then `tasks.parquet`, `stats.json` (recomputed over the whole dataset)
    /// and `info.json`, the metadata last so the dataset on disk is always whole. Nothing
    /// pending: nothing written.
    ///
    /// In a [`WriteMode::Overwrite`] session of an existing dataset the first flush is where
    /// the old `data/` and `meta/` are replaced (the old dataset stays until the new one has
    /// an episode); later flushes add to the new dataset.
    pub fn flush(&mut self) -> Result<()> {
        if self.new_rows.is_empty() {
            return Ok(());
        }
        let mut summary = self.write_all()?;
        if let Some(old_root) = self.replace.take() {
            swap_in(&self.root, &old_root)?;
            summary.data_file = summary
                .data_file
                .and_then(|p| p.strip_prefix(&self.root).ok().map(|r| old_root.join(r)));
            self.root = old_root;
        }
        self.last_data_file = summary.data_file;
        self.flushed += self.new_rows.len();
        self.existing.append(&mut self.new_rows);
        self.file_no += 1;
        Ok(())
    }

    /// Flush what is pending (see [`DatasetWriter::flush`]) and return the dataset's
    /// summary. A session that wrote nothing leaves an existing dataset as it was (a
    /// [`WriteMode::Overwrite`] one included); a new one gets its metadata with no episode.
    pub fn finish(mut self) -> Result<DatasetSummary> {
        if self.replace.is_some() && self.new_rows.is_empty() {
            let old = self.replace.clone().unwrap_or_default();
            let rows = read_episode_rows(&old).unwrap_or_default();
            return Ok(DatasetSummary {
                total_episodes: rows.len(),
                total_frames: rows.iter().map(|r| r.length).sum::<i64>() as usize,
                written_episodes: 0,
                data_file: None,
                set_aside: self.set_aside.clone(),
            });
        }
        if self.new_rows.is_empty() && self.flushed == 0 {
            return self.write_all();
        }
        self.flush()?;
        Ok(DatasetSummary {
            total_episodes: self.existing.len(),
            total_frames: self.existing.iter().map(|r| r.length).sum::<i64>() as usize,
            written_episodes: self.flushed,
            data_file: self.last_data_file.clone(),
            set_aside: self.set_aside.clone(),
        })
    }

    fn write_all(&mut self) -> Result<DatasetSummary> {
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
        let loaded = read_frames(&self.root, &all, &self.spec.keys)?;
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
            set_aside: self.set_aside.clone(),
        })
    }
}

impl Drop for DatasetWriter {
    /// An overwrite session that never finished leaves the old dataset as it was: remove
    /// its staging directory.
    fn drop(&mut self) {
        if self.replace.is_some() {
            let _ = fs::remove_dir_all(&self.root);
        }
    }
}

/// `<prefix>-<pid>-<nanos>`: a name no other writer uses.
fn unique_name(prefix: &str) -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    format!("{prefix}-{}-{nanos}", std::process::id())
}

/// Replace `root/{data,meta}` by `staging/{data,meta}`: the old ones are moved aside (meta
/// first, so the dataset is never a mix), the new ones moved in (meta last), then the old
/// ones and the staging directory are removed.
fn swap_in(staging: &Path, root: &Path) -> Result<()> {
    let aside = root.join(unique_name(".pir2-replaced"));
    fs::create_dir(&aside).map_err(|e| Error::io(&aside, e))?;
    for sub in ["meta", "data"] {
        let p = root.join(sub);
        if p.exists() {
            rename(&p, &aside.join(sub))?;
        }
    }
    for sub in ["data", "meta"] {
        let p = staging.join(sub);
        if p.exists() {
            rename(&p, &root.join(sub))?;
        }
    }
    fs::remove_dir_all(&aside).map_err(|e| Error::io(&aside, e))?;
    fs::remove_dir_all(staging).map_err(|e| Error::io(staging, e))
}

pub(super) fn max_file_number(dir: &Path) -> Result<Option<usize>> {
    Ok(file_numbers(dir, false)?.into_iter().max())
}

/// Numbers (`chunk · CHUNKS_SIZE + file`) of the `chunk-*/file-*` files under `dir`; with
/// `parquet_only`, only finished `.parquet` files (not `.tmp` leftovers).
pub(super) fn file_numbers(dir: &Path, parquet_only: bool) -> Result<Vec<usize>> {
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

pub(super) fn check_compatible(path: &Path, info: &Value, spec: &DatasetSpec) -> Result<()> {
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

pub(super) fn write_tasks(path: &Path, tasks: &[String]) -> Result<()> {
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
