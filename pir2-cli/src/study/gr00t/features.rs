//! `pir2 gr00t features`: the frozen GR00T N1.7 backbone run once over a LeRobotDataset
//! v3.0's camera videos, written as the features file `pir2 gr00t train --features` reads
//! (feature `gr00t`).
//!
//! For every frame of the dataset, episodes in `episode_index` order and frames in
//! `frame_index` order (the trainer's global frame order):
//! 1. the frame of each camera view named by the embodiment's `cameras` (camera features of
//!    the dataset, in view order) is read ([`FrameReader`]): a video feature is decoded
//!    from its video under LeRobot's timestamp rule (`from_timestamp + timestamp`, nearest
//!    decoded frame within `tolerance_s`); an image feature (PNG/JPEG bytes in the data
//!    files) is decoded from the frame's row. Both give the same RGB frame to step 3;
//! 2. the frame's task (`task_index` → `meta/tasks.parquet`) becomes the prompt as
//!    `pir2 gr00t run --task TASK` makes it (a key of the embodiment's `[tasks]`, else the
//!    text itself), through the checkpoint's tokenizer and GR00T N1.7's chat template;
//! 3. [`Gr00tBackbone::backbone_embeddings`] — the deployment backbone's own preprocessing
//!    and graphs (fused `backbone.onnx` or GR00T's split export), stopping before `vlln` and
//!    the VL self-attention, which the trainer applies itself — gives `[T, D_vl]`.
//!
//! The output is one safetensors file: `embeddings` F32 `[N, T, D_vl]`, `image_mask` and
//! `attention_mask` U8 `[N, T]` (0/1, the prompt's layout). It is written in place into
//! `OUT.partial` (its layout is fixed up front, rows go to their offsets), synced every few
//! seconds with a progress record `OUT.partial.json` (the frames done and the inputs), and
//! renamed to `OUT` when complete. `--resume` continues an interrupted run with the same
//! inputs; an existing `OUT` is replaced only with `--overwrite`. Memory holds one frame per
//! view and one row, never the dataset.

use std::fs::{File, OpenOptions};
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant, UNIX_EPOCH};

use anyhow::{bail, Context, Result};
use pir2_backends::gr00t::n17::train::tree_fingerprint;
use pir2_backends::gr00t::{load_tokenizer, CheckpointFiles, EmbodimentConfig, Gr00tBackbone};
use pir2_backends::ort::OrtOptions;
use pir2_sim::dataset::{check_ffmpeg, ffmpeg_program, FrameReader, VideoDataset};
use serde_json::{json, Value};

pub use super::Gr00tFeaturesOptions;

/// Progress of a run, reported after every frame.
#[derive(Debug, Clone)]
pub struct FeaturesProgress {
    /// Frames written (all runs).
    pub done: usize,
    /// Frames of the dataset.
    pub total: usize,
    /// Frames written by this run.
    pub this_run: usize,
    /// Seconds this run has taken.
    pub elapsed: f64,
    /// The episode being read.
    pub episode: i64,
}

/// What a run did.
#[derive(Debug, Clone)]
pub struct Gr00tFeaturesSummary {
    /// The finished file (or, when stopped, the partial one).
    pub path: PathBuf,
    /// Frames `N`, tokens `T`, width `D_vl`.
    pub shape: (usize, usize, usize),
    /// Frames already written when this run started (`--resume`).
    pub resumed_from: usize,
    /// Frames written when it ended.
    pub done: usize,
    /// Whether the file is complete (renamed to `OUT`).
    pub complete: bool,
    /// The backbone graphs run.
    pub backbone: String,
    /// The decoder program's version line.
    pub decoder: String,
}

impl Gr00tFeaturesSummary {
    /// Whether the run stopped before the end (resume with `--resume`).
    pub fn interrupted(&self) -> bool {
        !self.complete
    }
}

fn sibling(out: &Path, suffix: &str) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(suffix);
    out.with_file_name(name)
}

/// `OUT.partial`, the file being written.
pub fn partial_path(out: &Path) -> PathBuf {
    sibling(out, ".partial")
}

/// `OUT.partial.json`, the progress record of the file being written.
pub fn progress_path(out: &Path) -> PathBuf {
    sibling(out, ".partial.json")
}

/// Size and modification time of a file, for the inputs record (`None` if absent).
fn stamp(p: &Path) -> Option<Value> {
    let m = std::fs::metadata(p).ok()?;
    let mtime = m
        .modified()
        .ok()
        .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    Some(json!({"size": m.len(), "mtime_ns": mtime.to_string()}))
}

/// Every file under `dir` with its size and time (sorted), for the inputs record.
fn stamps_under(dir: &Path) -> Result<Value> {
    fn walk(dir: &Path, root: &Path, out: &mut Vec<(String, Value)>) -> Result<()> {
        let rd = match std::fs::read_dir(dir) {
            Ok(rd) => rd,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(e).with_context(|| format!("reading {}", dir.display())),
        };
        for e in rd {
            let p = e
                .with_context(|| format!("reading {}", dir.display()))?
                .path();
            if p.is_dir() {
                walk(&p, root, out)?;
            } else if let Some(s) = stamp(&p) {
                let rel = p.strip_prefix(root).unwrap_or(&p).display().to_string();
                out.push((rel, s));
            }
        }
        Ok(())
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v)?;
    v.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(Value::Object(v.into_iter().collect()))
}

/// The fixed layout of the output file.
struct Layout {
    header: Vec<u8>,
    frames: usize,
    tokens: usize,
    dim: usize,
}

impl Layout {
    fn new(frames: usize, tokens: usize, dim: usize) -> Result<Self> {
        let emb = frames
            .checked_mul(tokens)
            .and_then(|n| n.checked_mul(dim))
            .and_then(|n| n.checked_mul(4))
            .context("the features file would be larger than this machine can address")?;
        let mask = frames * tokens;
        // The producer names the command by its spelling of before `pir2 gr00t features`,
        // so files written now are byte for byte those of before (and so are their digests).
        let head = json!({
            "__metadata__": {"producer": "pir2 features gr00t", "format": "pt"},
            "embeddings": {"dtype": "F32", "shape": [frames, tokens, dim], "data_offsets": [0, emb]},
            "image_mask": {"dtype": "U8", "shape": [frames, tokens], "data_offsets": [emb, emb + mask]},
            "attention_mask": {"dtype": "U8", "shape": [frames, tokens], "data_offsets": [emb + mask, emb + 2 * mask]},
        });
        let mut text = serde_json::to_vec(&head)?;
        // 8-byte alignment of the data (what the safetensors writers do).
        while (8 + text.len()) % 8 != 0 {
            text.push(b' ');
        }
        let mut header = (text.len() as u64).to_le_bytes().to_vec();
        header.extend_from_slice(&text);
        Ok(Layout {
            header,
            frames,
            tokens,
            dim,
        })
    }
    fn data(&self) -> u64 {
        self.header.len() as u64
    }
    fn embedding_at(&self, i: usize) -> u64 {
        self.data() + (i * self.tokens * self.dim * 4) as u64
    }
    fn image_mask_at(&self, i: usize) -> u64 {
        self.data() + (self.frames * self.tokens * self.dim * 4 + i * self.tokens) as u64
    }
    fn attention_mask_at(&self, i: usize) -> u64 {
        self.data()
            + (self.frames * self.tokens * self.dim * 4
                + self.frames * self.tokens
                + i * self.tokens) as u64
    }
    fn len(&self) -> u64 {
        self.attention_mask_at(self.frames)
    }
}

fn write_at(f: &mut File, at: u64, bytes: &[u8], path: &Path) -> Result<()> {
    f.seek(SeekFrom::Start(at))
        .and_then(|_| f.write_all(bytes))
        .with_context(|| format!("writing {}", path.display()))
}

/// Write `value` to `path` atomically (temporary file, sync, rename).
fn write_json_atomic(path: &Path, value: &Value) -> Result<()> {
    let tmp = sibling(path, ".tmp");
    let mut f = File::create(&tmp).with_context(|| format!("writing {}", tmp.display()))?;
    f.write_all(serde_json::to_string_pretty(value)?.as_bytes())
        .and_then(|_| f.sync_all())
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming to {}", path.display()))
}

fn sync_dir(p: &Path) {
    if let Some(dir) = p.parent() {
        let dir = if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        };
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
}

/// Run the backbone over the dataset (see the module docs). `progress` is called after
/// every frame.
pub fn extract(
    o: &Gr00tFeaturesOptions,
    mut progress: impl FnMut(&FeaturesProgress),
) -> Result<Gr00tFeaturesSummary> {
    let out = &o.out;
    let (partial, record) = (partial_path(out), progress_path(out));
    if out.exists() && !o.overwrite {
        bail!("{} exists; pass --overwrite to replace it", out.display());
    }
    if !o.resume && (partial.exists() || record.exists()) {
        bail!(
            "an interrupted run left {} ({}); pass --resume to continue it, or delete both \
             files to start over",
            partial.display(),
            record.display()
        );
    }
    if !(o.tolerance_s.is_finite() && o.tolerance_s > 0.0) {
        bail!(
            "the timestamp tolerance must be > 0 s, got {}",
            o.tolerance_s
        );
    }

    // Inputs.
    let files = CheckpointFiles::in_dir(&o.checkpoint);
    let emb_path = o
        .embodiment
        .clone()
        .unwrap_or_else(|| files.embodiment.clone());
    let cfg = EmbodimentConfig::load(&emb_path)
        .with_context(|| format!("reading the embodiment {}", emb_path.display()))?;
    if cfg.cameras.is_empty() {
        bail!(
            "{}: `cameras` names no camera view; list the dataset's camera (video or image) \
             features in view order, one per prompt.chat.images ({}), e.g. cameras = \
             [\"observation.images.ego_view\"]",
            emb_path.display(),
            cfg.prompt.chat.images
        );
    }
    let data = VideoDataset::open(&o.data)
        .with_context(|| format!("reading the dataset {}", o.data.display()))?;
    data.check_views(&cfg.cameras)?;
    if data.tasks.is_empty() {
        bail!(
            "{}: the dataset has no tasks (meta/tasks.parquet): the backbone needs each \
             frame's instruction",
            o.data.display()
        );
    }
    let total = data.total_frames();
    if total == 0 {
        bail!("{}: the dataset has no frames", o.data.display());
    }
    let program = ffmpeg_program();
    let decoder = if data.needs_video_decoder(&cfg.cameras) {
        check_ffmpeg(&program)?
    } else {
        "none (image features only)".to_string()
    };
    let tok = load_tokenizer(&files, &cfg.prompt)?;
    let first_prompt = cfg.prompt_for(data.task(&data.episodes[0], 0)).to_string();
    let mut bb = Gr00tBackbone::load(
        &files,
        &cfg.image,
        &cfg.prompt,
        &cfg.vision,
        tok.as_ref(),
        &first_prompt,
        None,
        &OrtOptions {
            intra_threads: o.threads.max(1),
            ..o.ep.ort()?
        },
    )
    .with_context(|| format!("loading the backbone of {}", o.checkpoint.display()))?;
    let (tokens, dim) = bb.output_shape();
    let layout = Layout::new(total, tokens, dim)?;

    let mut backbone_files = serde_json::Map::new();
    for p in [
        &files.backbone,
        &files.vit,
        &files.llm,
        &files.model_weights,
        &files.model_index,
        &files.tokenizer,
        &files.vocab,
    ] {
        if let Some(s) = stamp(p) {
            backbone_files.insert(p.display().to_string(), s);
        }
    }
    let inputs = json!({
        "dataset": tree_fingerprint(&o.data, &["meta", "data"])?,
        "videos": stamps_under(&o.data.join("videos"))?,
        "checkpoint": backbone_files,
        "embodiment": {
            "cameras": cfg.cameras,
            "image": serde_json::to_value(&cfg.image)?,
            "prompt": serde_json::to_value(&cfg.prompt)?,
            "vision": serde_json::to_value(&cfg.vision)?,
            "tasks": serde_json::to_value(&cfg.tasks)?,
        },
        "tolerance_s": o.tolerance_s,
        "shape": [total, tokens, dim],
    });

    // The partial file: continue it, or lay it out.
    let mut start = 0;
    let mut f = if o.resume && partial.exists() && record.exists() {
        let text = std::fs::read_to_string(&record)
            .with_context(|| format!("reading {}", record.display()))?;
        let rec: Value =
            serde_json::from_str(&text).with_context(|| format!("reading {}", record.display()))?;
        if rec.get("inputs") != Some(&inputs) {
            bail!(
                "{} was written from other inputs (dataset, videos, checkpoint, embodiment or \
                 tolerance changed); delete it and {} to start over",
                partial.display(),
                record.display()
            );
        }
        start = rec
            .get("frames_done")
            .and_then(Value::as_u64)
            .with_context(|| format!("{}: no frames_done", record.display()))?
            as usize;
        let f = OpenOptions::new()
            .read(true)
            .write(true)
            .open(&partial)
            .with_context(|| format!("opening {}", partial.display()))?;
        let len = f
            .metadata()
            .with_context(|| format!("reading {}", partial.display()))?
            .len();
        if start > total || len != layout.len() {
            bail!(
                "{} does not have the layout its record {} describes ({} bytes, {} of {} \
                 frames); delete both to start over",
                partial.display(),
                record.display(),
                len,
                start,
                total
            );
        }
        f
    } else {
        if o.resume && (partial.exists() != record.exists()) {
            bail!(
                "only one of {} and {} exists; delete it to start over",
                partial.display(),
                record.display()
            );
        }
        let mut f =
            File::create(&partial).with_context(|| format!("creating {}", partial.display()))?;
        f.set_len(layout.len())
            .with_context(|| format!("sizing {}", partial.display()))?;
        write_at(&mut f, 0, &layout.header, &partial)?;
        f.sync_all()
            .with_context(|| format!("writing {}", partial.display()))?;
        write_json_atomic(&record, &json!({"frames_done": 0, "inputs": inputs}))?;
        f
    };

    let mut readers: Vec<FrameReader> = cfg
        .cameras
        .iter()
        .map(|_| FrameReader::new(program.clone(), o.tolerance_s))
        .collect();
    let mut prompt = first_prompt;
    let mut row = Vec::<u8>::with_capacity(tokens * dim * 4);
    let t0 = Instant::now();
    let mut last_sync = Instant::now();
    let mut done = start;
    let mut global = 0;
    let stopped = |n: usize| {
        o.stop.as_ref().is_some_and(|s| s.load(Ordering::Relaxed))
            || o.stop_after.is_some_and(|k| n >= k)
    };
    let checkpoint = |f: &mut File, done: usize| -> Result<()> {
        f.sync_data()
            .with_context(|| format!("writing {}", partial.display()))?;
        write_json_atomic(&record, &json!({"frames_done": done, "inputs": inputs}))
    };
    'episodes: for ep in &data.episodes {
        if global + ep.len() <= start {
            global += ep.len();
            continue;
        }
        for t in 0..ep.len() {
            if global < start {
                global += 1;
                continue;
            }
            if stopped(done - start) {
                break 'episodes;
            }
            let want = cfg.prompt_for(data.task(ep, t));
            if want != prompt {
                bb.set_prompt(&files, &cfg.prompt, tok.as_ref(), want)
                    .with_context(|| format!("the prompt of episode {}", ep.episode_index))?;
                prompt = want.to_string();
            }
            let mut views = Vec::with_capacity(readers.len());
            for (r, key) in readers.iter_mut().zip(&cfg.cameras) {
                let fr = r.frame(&data, key, ep, t)?;
                views.push((fr.rgb.as_slice(), fr.hw));
            }
            let e = bb.backbone_embeddings(&views).with_context(|| {
                format!("the backbone on episode {}, frame {t}", ep.episode_index)
            })?;
            row.clear();
            for v in e {
                row.extend_from_slice(&v.to_le_bytes());
            }
            let lay = bb.layout();
            let image: Vec<u8> = lay.image_mask.iter().map(|&b| u8::from(b)).collect();
            let attn: Vec<u8> = lay.attention_mask.iter().map(|&b| u8::from(b)).collect();
            write_at(&mut f, layout.embedding_at(global), &row, &partial)?;
            write_at(&mut f, layout.image_mask_at(global), &image, &partial)?;
            write_at(&mut f, layout.attention_mask_at(global), &attn, &partial)?;
            global += 1;
            done += 1;
            if last_sync.elapsed() > Duration::from_secs(10) {
                checkpoint(&mut f, done)?;
                last_sync = Instant::now();
            }
            progress(&FeaturesProgress {
                done,
                total,
                this_run: done - start,
                elapsed: t0.elapsed().as_secs_f64(),
                episode: ep.episode_index,
            });
        }
    }
    checkpoint(&mut f, done)?;
    let complete = done == total;
    if complete {
        drop(f);
        std::fs::rename(&partial, out)
            .with_context(|| format!("renaming {} to {}", partial.display(), out.display()))?;
        sync_dir(out);
        let _ = std::fs::remove_file(&record);
    }
    Ok(Gr00tFeaturesSummary {
        path: if complete { out.clone() } else { partial },
        shape: (total, tokens, dim),
        resumed_from: start,
        done,
        complete,
        backbone: bb.describe(),
        decoder,
    })
}
