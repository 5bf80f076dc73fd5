//! Camera frames of a LeRobotDataset v3.0, decoded from its videos.
//!
//! # Where a frame is (LeRobot v3.0)
//!
//! A video feature (`"dtype": "video"` in `meta/info.json`) is stored as MP4 files at
//! `video_path` (default `videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4`),
//! several episodes one after the other in one file. Each episode's row in `meta/episodes`
//! names its file (`videos/<key>/chunk_index`, `videos/<key>/file_index`) and where it starts
//! in it (`videos/<key>/from_timestamp`, s). Frame `t` of an episode is the decoded frame
//! whose presentation time (`pts · time_base`) is nearest to `from_timestamp + timestamp_t`
//! (`timestamp` is the frame's column in `data/`, `frame_index / fps` as LeRobot writes it),
//! and it must lie closer than the tolerance ([`DEFAULT_TOLERANCE_S`], LeRobot's
//! `tolerance_s`); otherwise the frame is missing and [`Error::VideoFrame`] names the file,
//! the episode, the frame and the nearest decoded frame.
//!
//! # Decoding
//!
//! The `ffmpeg` program decodes (one process per view, streaming; `PIR2_FFMPEG` names another
//! program): `-copyts` keeps the file's own timestamps, `-fps_mode passthrough` emits every
//! decoded frame once, `showinfo` reports each frame's `pts` and the stream's time base on
//! stderr, and the frames come out as raw `rgb24` on stdout. This is the conversion PyAV's
//! `frame.to_ndarray(format="rgb24")` (LeRobot's decoding backend) does, with the same
//! libswscale defaults; the test compares both. FFmpeg decodes every codec LeRobot writes
//! (AV1, its default since v3.0, through libdav1d; H.264 of older sets; HEVC), which no
//! pure-Rust decoder does today. A missing `ffmpeg`, or one older than 5.1 (no
//! `-fps_mode`), is one [`Error::FfmpegMissing`].
//!
//! Frames are read in order. A stream is started at a seek point shortly before the first
//! frame asked for (`-ss`, input side) and read forward; asking for an earlier time or for
//! another file starts a new one. At most one frame per view is kept in memory besides the
//! one being read.
//!
//! # Image features
//!
//! A camera may instead be an image feature (`"dtype": "image"`): LeRobot v3.0 writes it
//! into the data files themselves (`data_path`), one encoded image per frame in the
//! feature's column, as Hugging Face `datasets`' `Image` type stores it: a struct of
//! `bytes` (the PNG file LeRobot's image writer made, or another format) and `path` (the
//! name it had). LeRobot decodes it with Pillow and hands the pixels on unchanged. Here
//! the frame of row `(episode_index, frame_index)` is decoded with the pure-Rust `image`
//! crate (PNG, JPEG) into the same `height × width × 3` RGB frame a video gives, as
//! Pillow's `convert("RGB")` of an 8-bit image: grey replicated, alpha dropped. 16-bit and
//! float images, a missing `bytes` value and bytes that do not decode are one
//! [`Error::ImageFrame`] naming the data file, the camera, the episode and the frame. The
//! reader keeps one data file's column of one camera in memory.
//!
//! # Depth
//!
//! LeRobot v3.0 marks a depth camera's video with `"video.is_depth_map": true` in its
//! feature's `info` (`video_info` in older sets; newer LeRobot versions quantise depth into
//! 12-bit video). The backbone
//! takes RGB cameras only: [`VideoDataset::check_views`] refuses a depth camera by name.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::sync::{Arc, Mutex};

use arrow_array::cast::AsArray;
use arrow_array::types::{Float32Type, Float64Type};
use arrow_array::{Array, RecordBatch};
use arrow_schema::DataType;
use serde_json::Value;

use super::read::{
    check_template, column, int_column, read_episode_rows, read_info_checked, read_parquet,
    read_parquet_columns, read_tasks, type_error,
};
use super::write::fill_template;
use super::{INFO_PATH, TASKS_PATH};
use crate::error::{Error, Result};

/// LeRobot's default `video_path` template.
pub const VIDEO_PATH: &str = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";

/// LeRobot's default timestamp tolerance (`LeRobotDataset(tolerance_s=1e-4)`), s.
pub const DEFAULT_TOLERANCE_S: f64 = 1e-4;

/// How far before the first frame asked for a stream starts decoding, s (`-ss`; ffmpeg
/// decodes from the key frame before it and drops what lies before the seek point).
const SEEK_MARGIN_S: f64 = 0.5;

/// Reading forward further than this to the next frame asked for starts a new, seeking
/// stream instead, s.
const MAX_READ_AHEAD_S: f64 = 2.0;

/// Largest frame accepted from a video (pixels), against a malformed decoder report.
const MAX_PIXELS: usize = 1 << 26;

/// Where one episode lies in one view's video.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VideoSpan {
    /// `videos/<key>/chunk_index`.
    pub chunk_index: i64,
    /// `videos/<key>/file_index`.
    pub file_index: i64,
    /// `videos/<key>/from_timestamp`, s: the episode's start in the file.
    pub from_timestamp: f64,
}

/// One episode's frames: their timestamps and tasks, and its place in each view's video.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoEpisode {
    /// `episode_index`.
    pub episode_index: i64,
    /// Per frame (in `frame_index` order): the `timestamp` column, s.
    pub timestamps: Vec<f64>,
    /// Per frame: `task_index`.
    pub task_index: Vec<i64>,
    /// Per video feature: where the episode is.
    pub videos: BTreeMap<String, VideoSpan>,
    /// The data file holding the episode's rows (`data/chunk_index`, `data/file_index`):
    /// where its image features are.
    pub data_file: (i64, i64),
}

impl VideoEpisode {
    /// Frames.
    pub fn len(&self) -> usize {
        self.timestamps.len()
    }

    /// No frames.
    pub fn is_empty(&self) -> bool {
        self.timestamps.is_empty()
    }
}

/// A LeRobotDataset v3.0's frame index for its camera videos (metadata only: timestamps,
/// tasks, video files; no image is read until [`FrameReader`] asks for it).
#[derive(Debug, Clone)]
pub struct VideoDataset {
    root: PathBuf,
    /// Frames per second (`info.json`).
    pub fps: f64,
    /// The video features, in `info.json` order.
    pub video_keys: Vec<String>,
    /// The image features (encoded images in the data files), in `info.json` order.
    pub image_keys: Vec<String>,
    /// The video features marked `video.is_depth_map`.
    pub depth_keys: Vec<String>,
    /// Task strings by `task_index`.
    pub tasks: Vec<String>,
    /// Episodes in `episode_index` order.
    pub episodes: Vec<VideoEpisode>,
    video_tmpl: String,
    data_tmpl: String,
}

fn f64_column(batch: &RecordBatch, path: &Path, name: &str) -> Result<Vec<f64>> {
    let a = column(batch, path, name)?;
    if a.null_count() > 0 {
        return Err(type_error(path, name, "no null rows", a.data_type()));
    }
    Ok(match a.data_type() {
        DataType::Float64 => a.as_primitive::<Float64Type>().values().to_vec(),
        DataType::Float32 => a
            .as_primitive::<Float32Type>()
            .values()
            .iter()
            .map(|v| f64::from(*v))
            .collect(),
        t => return Err(type_error(path, name, "float32 or float64", t)),
    })
}

impl VideoDataset {
    /// Read the frame index of the dataset at `root`: `meta/info.json` (v3.x, its
    /// `video_path` template checked), `meta/episodes` (with each video feature's
    /// `videos/<key>/…` columns), `meta/tasks.parquet`, and the `episode_index`,
    /// `frame_index`, `timestamp` and `task_index` columns of `data/`.
    pub fn open(root: &Path) -> Result<Self> {
        let (info, fps, data_tmpl) = read_info_checked(root)?;
        let info_path = root.join(INFO_PATH);
        let video_tmpl = match info.get("video_path") {
            Some(Value::String(t)) => {
                check_template(
                    &info_path,
                    "video_path",
                    t,
                    &["video_key", "chunk_index", "file_index"],
                )?;
                t.clone()
            }
            _ => VIDEO_PATH.to_string(),
        };
        let video_keys: Vec<String> = info
            .get("features")
            .and_then(Value::as_object)
            .map(|f| {
                f.iter()
                    .filter(|(_, v)| v.get("dtype").and_then(Value::as_str) == Some("video"))
                    .map(|(k, _)| k.clone())
                    .collect()
            })
            .unwrap_or_default();
        let features = info.get("features").and_then(Value::as_object);
        let keys_where = |pred: &dyn Fn(&Value) -> bool| -> Vec<String> {
            features
                .map(|f| {
                    f.iter()
                        .filter(|(_, v)| pred(v))
                        .map(|(k, _)| k.clone())
                        .collect()
                })
                .unwrap_or_default()
        };
        let image_keys = keys_where(&|v| v.get("dtype").and_then(Value::as_str) == Some("image"));
        let depth_keys = keys_where(&|v| {
            v.get("dtype").and_then(Value::as_str) == Some("video")
                && ["info", "video_info"]
                    .iter()
                    .find_map(|k| v.get(*k))
                    .and_then(|i| i.get("video.is_depth_map"))
                    .and_then(Value::as_bool)
                    .unwrap_or(false)
        });
        for k in &video_keys {
            if k.is_empty() || k.contains(['/', '\\', '\0']) || k == ".." || k == "." {
                return Err(Error::Feature {
                    path: info_path.clone(),
                    key: k.clone(),
                    reason: "is not usable as a path segment of `video_path`".into(),
                });
            }
        }
        let rows = read_episode_rows(root)?;
        let spans = read_video_spans(root, &video_keys)?;
        let tasks_path = root.join(TASKS_PATH);
        let tasks = if tasks_path.exists() {
            read_tasks(&tasks_path)?
        } else {
            Vec::new()
        };

        // Frames: timestamps and tasks, grouped by episode.
        let mut files = std::collections::BTreeSet::new();
        for r in &rows {
            files.insert((r.data_chunk, r.data_file));
        }
        type Frames = (Vec<i64>, Vec<f64>, Vec<i64>);
        let mut by_ep: BTreeMap<i64, Frames> = BTreeMap::new();
        for &(chunk, file) in &files {
            let path = root.join(fill_template(&data_tmpl, chunk as usize, file as usize));
            let keep = ["episode_index", "frame_index", "timestamp", "task_index"];
            for b in read_parquet_columns(&path, Some(&keep))? {
                let ep = int_column(&b, &path, "episode_index")?;
                let frame = int_column(&b, &path, "frame_index")?;
                let ts = if b.column_by_name("timestamp").is_some() {
                    f64_column(&b, &path, "timestamp")?
                } else {
                    frame.iter().map(|f| *f as f64 / fps).collect()
                };
                let task = if b.column_by_name("task_index").is_some() {
                    int_column(&b, &path, "task_index")?
                } else {
                    vec![0; b.num_rows()]
                };
                for i in 0..b.num_rows() {
                    let e = by_ep.entry(ep[i]).or_default();
                    e.0.push(frame[i]);
                    e.1.push(ts[i]);
                    e.2.push(task[i]);
                }
            }
        }
        let mut episodes = Vec::with_capacity(rows.len());
        for r in &rows {
            let data_path = root.join(fill_template(
                &data_tmpl,
                r.data_chunk as usize,
                r.data_file as usize,
            ));
            let bad = |reason: String| Error::Inconsistent {
                path: data_path.clone(),
                reason,
            };
            let (frames, timestamps, task_index) =
                by_ep.remove(&r.episode_index).ok_or_else(|| {
                    bad(format!(
                        "episode {} listed in meta/episodes has no frames",
                        r.episode_index
                    ))
                })?;
            if frames.len() as i64 != r.length {
                return Err(bad(format!(
                    "episode {} has {} frames, meta/episodes says {}",
                    r.episode_index,
                    frames.len(),
                    r.length
                )));
            }
            if frames.iter().enumerate().any(|(t, f)| *f != t as i64) {
                return Err(bad(format!(
                    "episode {}: frame_index is not 0, 1, 2, … in file order",
                    r.episode_index
                )));
            }
            if let Some((t, ts)) = timestamps.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(bad(format!(
                    "episode {} frame {t}: timestamp is {ts}",
                    r.episode_index
                )));
            }
            if let Some((t, k)) = task_index
                .iter()
                .enumerate()
                .find(|(_, k)| **k < 0 || (!tasks.is_empty() && **k as usize >= tasks.len()))
            {
                return Err(bad(format!(
                    "episode {} frame {t}: task_index {k} is not one of the {} tasks of {}",
                    r.episode_index,
                    tasks.len(),
                    TASKS_PATH
                )));
            }
            let videos = spans.get(&r.episode_index).cloned().unwrap_or_default();
            episodes.push(VideoEpisode {
                episode_index: r.episode_index,
                timestamps,
                task_index,
                videos,
                data_file: (r.data_chunk, r.data_file),
            });
        }
        Ok(VideoDataset {
            root: root.to_path_buf(),
            fps,
            video_keys,
            image_keys,
            depth_keys,
            tasks,
            episodes,
            video_tmpl,
            data_tmpl,
        })
    }

    /// The dataset's root directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Total frames.
    pub fn total_frames(&self) -> usize {
        self.episodes.iter().map(VideoEpisode::len).sum()
    }

    /// Check that every key of `views` is an RGB camera: an image feature, or a video
    /// feature (not a depth map) with a file for every episode (one [`Error::Feature`]
    /// naming the key and, when it is not a camera, the cameras there are).
    pub fn check_views(&self, views: &[String]) -> Result<()> {
        let info = self.root.join(INFO_PATH);
        let list = |keys: &[String]| {
            if keys.is_empty() {
                "none".to_string()
            } else {
                keys.join(", ")
            }
        };
        for v in views {
            if self.depth_keys.contains(v) {
                return Err(Error::Feature {
                    path: info,
                    key: v.clone(),
                    reason: "is a depth video (`video.is_depth_map`); the backbone takes RGB \
                             cameras and pir2 does not read depth maps"
                        .into(),
                });
            }
            if self.is_image(v) {
                continue;
            }
            if !self.video_keys.contains(v) {
                return Err(Error::Feature {
                    path: info,
                    key: v.clone(),
                    reason: format!(
                        "is not a camera feature of the dataset (its video features: {}; its \
                         image features: {})",
                        list(&self.video_keys),
                        list(&self.image_keys)
                    ),
                });
            }
            if let Some(e) = self.episodes.iter().find(|e| !e.videos.contains_key(v)) {
                return Err(Error::Feature {
                    path: self.root.join("meta/episodes"),
                    key: v.clone(),
                    reason: format!(
                        "has no `videos/{v}/chunk_index`, `file_index` and `from_timestamp` for episode {}",
                        e.episode_index
                    ),
                });
            }
        }
        Ok(())
    }

    /// The video file of view `key` for `episode`.
    pub fn video_file(&self, key: &str, episode: &VideoEpisode) -> Result<PathBuf> {
        let span = episode.videos.get(key).ok_or_else(|| Error::Feature {
            path: self.root.join("meta/episodes"),
            key: key.to_string(),
            reason: format!("has no video for episode {}", episode.episode_index),
        })?;
        let rel = self.video_tmpl.replace("{video_key}", key);
        Ok(self.root.join(fill_template(
            &rel,
            span.chunk_index as usize,
            span.file_index as usize,
        )))
    }

    /// Whether camera `key` is an image feature (else a video feature).
    pub fn is_image(&self, key: &str) -> bool {
        self.image_keys.iter().any(|k| k == key)
    }

    /// Whether any of `views` is a video feature (and so needs the decoder program).
    pub fn needs_video_decoder(&self, views: &[String]) -> bool {
        views.iter().any(|v| self.video_keys.contains(v))
    }

    /// The data file holding `episode`'s rows.
    pub fn data_file(&self, episode: &VideoEpisode) -> PathBuf {
        self.root.join(fill_template(
            &self.data_tmpl,
            episode.data_file.0 as usize,
            episode.data_file.1 as usize,
        ))
    }

    /// The task string of frame `t` of `episode` (`meta/tasks.parquet`; empty if the
    /// dataset has no task table).
    pub fn task(&self, episode: &VideoEpisode, t: usize) -> &str {
        let k = episode.task_index[t];
        self.tasks.get(k as usize).map_or("", String::as_str)
    }
}

/// Per episode and video feature: the `videos/<key>/…` columns of `meta/episodes`.
fn read_video_spans(
    root: &Path,
    keys: &[String],
) -> Result<BTreeMap<i64, BTreeMap<String, VideoSpan>>> {
    let mut out: BTreeMap<i64, BTreeMap<String, VideoSpan>> = BTreeMap::new();
    if keys.is_empty() {
        return Ok(out);
    }
    let dir = root.join("meta/episodes");
    let mut files = Vec::new();
    for c in std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))? {
        let c = c.map_err(|e| Error::io(&dir, e))?.path();
        if let Ok(rd) = std::fs::read_dir(&c) {
            for f in rd {
                let p = f.map_err(|e| Error::io(&c, e))?.path();
                if p.extension().is_some_and(|e| e == "parquet") {
                    files.push(p);
                }
            }
        }
    }
    files.sort();
    for path in files {
        for b in read_parquet(&path)? {
            let ep = int_column(&b, &path, "episode_index")?;
            for k in keys {
                let chunk = format!("videos/{k}/chunk_index");
                if b.column_by_name(&chunk).is_none() {
                    continue;
                }
                let chunk = int_column(&b, &path, &chunk)?;
                let file = int_column(&b, &path, &format!("videos/{k}/file_index"))?;
                let from = f64_column(&b, &path, &format!("videos/{k}/from_timestamp"))?;
                for i in 0..b.num_rows() {
                    if chunk[i] < 0 || file[i] < 0 || !from[i].is_finite() || from[i] < 0.0 {
                        return Err(Error::Inconsistent {
                            path: path.clone(),
                            reason: format!(
                                "episode {}: videos/{k}/ chunk_index {}, file_index {}, \
                                 from_timestamp {} (must be ≥ 0)",
                                ep[i], chunk[i], file[i], from[i]
                            ),
                        });
                    }
                    out.entry(ep[i]).or_default().insert(
                        k.clone(),
                        VideoSpan {
                            chunk_index: chunk[i],
                            file_index: file[i],
                            from_timestamp: from[i],
                        },
                    );
                }
            }
        }
    }
    Ok(out)
}

// ------------------------------------------------------------------------ decoding

/// One decoded frame: HWC `u8` RGB and its presentation time.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedFrame {
    /// Presentation time, s (`pts · time_base`, the file's own clock).
    pub time: f64,
    /// `(height, width)`.
    pub hw: (usize, usize),
    /// `height × width × 3` bytes, row-major RGB.
    pub rgb: Vec<u8>,
}

/// What the decoder reports per frame on stderr (`showinfo`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FrameInfo {
    pub(crate) time: f64,
    pub(crate) hw: (usize, usize),
}

/// Parse one `showinfo` line: the stream's time base (`config in time_base: N/D`) or a
/// frame (`n: … pts: P … s:WxH`). Returns the new time base or a frame.
pub(crate) fn parse_showinfo(
    line: &str,
    time_base: Option<(i64, i64)>,
) -> Option<std::result::Result<ShowInfo, String>> {
    if !line.contains("Parsed_showinfo") {
        return None;
    }
    if let Some(rest) = line.split("config in time_base:").nth(1) {
        let tb = rest.split(',').next().unwrap_or("").trim();
        let parsed = tb
            .split_once('/')
            .and_then(|(n, d)| Some((n.trim().parse::<i64>().ok()?, d.trim().parse::<i64>().ok()?)))
            .filter(|(n, d)| *n > 0 && *d > 0);
        return Some(match parsed {
            Some(tb) => Ok(ShowInfo::TimeBase(tb)),
            None => Err(format!("unreadable time base `{tb}`")),
        });
    }
    let body = line.split_once(']').map_or(line, |(_, b)| b);
    if !body.trim_start().starts_with("n:") {
        return None;
    }
    let field = |name: &str| -> Option<&str> {
        let mut it = body.split_whitespace();
        while let Some(tok) = it.next() {
            if let Some(v) = tok.strip_prefix(name) {
                return if v.is_empty() { it.next() } else { Some(v) };
            }
        }
        None
    };
    let Some((num, den)) = time_base else {
        return Some(Err("a frame before the time base".into()));
    };
    let pts = match field("pts:").map(str::parse::<i64>) {
        Some(Ok(p)) => p,
        _ => {
            return Some(Err(format!(
                "a frame without a usable pts: `{}`",
                body.trim()
            )))
        }
    };
    let hw = field("s:")
        .and_then(|s| s.split_once('x'))
        .and_then(|(w, h)| Some((h.parse::<usize>().ok()?, w.parse::<usize>().ok()?)))
        .filter(|(h, w)| *h > 0 && *w > 0 && h.checked_mul(*w).is_some_and(|p| p <= MAX_PIXELS));
    let Some(hw) = hw else {
        return Some(Err(format!(
            "a frame without a usable size: `{}`",
            body.trim()
        )));
    };
    // pts · num / den without losing precision for long files.
    let time = (pts as f64) * (num as f64) / (den as f64);
    Some(Ok(ShowInfo::Frame(FrameInfo { time, hw })))
}

/// A parsed `showinfo` line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum ShowInfo {
    TimeBase((i64, i64)),
    Frame(FrameInfo),
}

/// The program that decodes: `$PIR2_FFMPEG`, else `ffmpeg` on the `PATH`.
pub fn ffmpeg_program() -> PathBuf {
    std::env::var_os("PIR2_FFMPEG")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("ffmpeg"))
}

/// Check that the decoder program runs (`ffmpeg -version`); returns its first output line.
pub fn check_ffmpeg(program: &Path) -> Result<String> {
    let out = Command::new(program)
        .arg("-hide_banner")
        .arg("-version")
        .stdin(Stdio::null())
        .output()
        .map_err(|source| Error::FfmpegMissing {
            program: program.to_path_buf(),
            source,
        })?;
    if !out.status.success() {
        return Err(Error::FfmpegMissing {
            program: program.to_path_buf(),
            source: std::io::Error::other(format!("`-version` exited with {}", out.status)),
        });
    }
    let first = String::from_utf8_lossy(&out.stdout)
        .lines()
        .next()
        .unwrap_or("")
        .to_string();
    if let Some((major, minor)) = ffmpeg_version(&first) {
        if (major, minor) < (5, 1) {
            return Err(Error::FfmpegMissing {
                program: program.to_path_buf(),
                source: std::io::Error::other(format!(
                    "it is version {major}.{minor}; at least 5.1 is needed (`-fps_mode`)"
                )),
            });
        }
    }
    Ok(first)
}

/// `(major, minor)` of an `ffmpeg -version` first line (`ffmpeg version 5.1.9-0+deb12u1 …`);
/// `None` for a version that is not numbered (a development build).
fn ffmpeg_version(line: &str) -> Option<(u32, u32)> {
    let v = line.split("version ").nth(1)?.split_whitespace().next()?;
    let v = v.trim_start_matches('n');
    let mut it = v.split(|c: char| !c.is_ascii_digit());
    let major = it.next()?.parse().ok()?;
    let minor = it.next().and_then(|m| m.parse().ok()).unwrap_or(0);
    Some((major, minor))
}

enum Msg {
    Frame(FrameInfo),
    Bad(String),
}

/// One view's frames from one video file, decoded by `ffmpeg` from a start time on.
pub struct VideoStream {
    path: PathBuf,
    child: Child,
    out: BufReader<ChildStdout>,
    info: Receiver<Msg>,
    log: Arc<Mutex<Vec<String>>>,
    /// The last frame before the next one, and the next one.
    prev: Option<DecodedFrame>,
    next: Option<DecodedFrame>,
    ended: bool,
}

impl std::fmt::Debug for VideoStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoStream")
            .field("path", &self.path)
            .field("next", &self.next.as_ref().map(|f| f.time))
            .field("ended", &self.ended)
            .finish()
    }
}

impl VideoStream {
    /// Start decoding `path` with `program` from about `start` s on (the file's own
    /// timestamps; frames from the seek point `start − 0.5 s` on are decoded).
    pub fn open(program: &Path, path: &Path, start: f64) -> Result<Self> {
        if !path.is_file() {
            return Err(Error::MissingFile {
                path: path.to_path_buf(),
            });
        }
        let seek = (start - SEEK_MARGIN_S).max(0.0);
        let mut cmd = Command::new(program);
        cmd.args(["-hide_banner", "-nostdin", "-nostats", "-loglevel", "info"]);
        if seek > 0.0 {
            cmd.args(["-ss", &format!("{seek:.6}")]);
        }
        cmd.arg("-copyts")
            .arg("-i")
            .arg(path)
            .args([
                "-map",
                "0:v:0",
                "-an",
                "-vf",
                "showinfo",
                "-fps_mode",
                "passthrough",
                "-f",
                "rawvideo",
                "-pix_fmt",
                "rgb24",
                "-",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = cmd.spawn().map_err(|source| Error::FfmpegMissing {
            program: program.to_path_buf(),
            source,
        })?;
        let stdout = child.stdout.take().expect("piped");
        let stderr = child.stderr.take().expect("piped");
        let (tx, rx) = mpsc::channel();
        let log = Arc::new(Mutex::new(Vec::new()));
        let log2 = Arc::clone(&log);
        std::thread::spawn(move || {
            let mut tb = None;
            let mut r = BufReader::new(stderr);
            let mut buf = Vec::new();
            loop {
                buf.clear();
                match r.read_until(b'\n', &mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {}
                }
                let text = String::from_utf8_lossy(&buf);
                for line in text.split('\r') {
                    match parse_showinfo(line, tb) {
                        Some(Ok(ShowInfo::TimeBase(t))) => tb = Some(t),
                        Some(Ok(ShowInfo::Frame(f))) => {
                            if tx.send(Msg::Frame(f)).is_err() {
                                return;
                            }
                        }
                        Some(Err(m)) => {
                            let _ = tx.send(Msg::Bad(m));
                        }
                        None => {
                            let l = line.trim();
                            if !l.is_empty() && !l.contains("Parsed_showinfo") {
                                if let Ok(mut g) = log2.lock() {
                                    g.push(l.to_string());
                                    let n = g.len();
                                    if n > 8 {
                                        g.drain(..n - 8);
                                    }
                                }
                            }
                        }
                    }
                }
            }
        });
        Ok(VideoStream {
            path: path.to_path_buf(),
            child,
            out: BufReader::with_capacity(1 << 20, stdout),
            info: rx,
            log,
            prev: None,
            next: None,
            ended: false,
        })
    }

    /// The video file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn fail(&self, what: impl std::fmt::Display) -> Error {
        let log = self.log.lock().map(|g| g.join(" | ")).unwrap_or_default();
        Error::Video {
            path: self.path.clone(),
            reason: if log.is_empty() {
                what.to_string()
            } else {
                format!("{what} (ffmpeg: {log})")
            },
        }
    }

    /// Decode the next frame into `slot` (reusing its buffer); `false` at the end.
    fn read_frame(&mut self, slot: &mut Option<DecodedFrame>) -> Result<bool> {
        if self.ended {
            return Ok(false);
        }
        match self.info.recv() {
            Ok(Msg::Frame(fi)) => {
                let n = fi.hw.0 * fi.hw.1 * 3;
                let mut f = slot.take().unwrap_or(DecodedFrame {
                    time: 0.0,
                    hw: (0, 0),
                    rgb: Vec::new(),
                });
                f.rgb.resize(n, 0);
                self.out.read_exact(&mut f.rgb).map_err(|e| {
                    self.fail(format!(
                        "the decoder reported a {}×{} frame at {:.6} s but its pixels could not be read ({e})",
                        fi.hw.1, fi.hw.0, fi.time
                    ))
                })?;
                f.time = fi.time;
                f.hw = fi.hw;
                *slot = Some(f);
                Ok(true)
            }
            Ok(Msg::Bad(m)) => Err(self.fail(m)),
            Err(_) => {
                self.ended = true;
                let status = self.child.wait().map_err(|e| Error::io(&self.path, e))?;
                let mut rest = [0u8; 1];
                let extra = self.out.read(&mut rest).unwrap_or(0);
                if !status.success() {
                    return Err(self.fail(format!("ffmpeg exited with {status}")));
                }
                if extra > 0 {
                    return Err(self.fail("the decoder wrote pixels it did not report"));
                }
                Ok(false)
            }
        }
    }

    /// The decoded frame nearest to `time` (s, the file's clock) if it lies closer than
    /// `tolerance` (LeRobot's rule), else `Err(nearest)` describing the nearest decoded
    /// frame. Times asked for must not decrease.
    pub fn frame_at(
        &mut self,
        time: f64,
        tolerance: f64,
    ) -> Result<std::result::Result<&DecodedFrame, String>> {
        if self.next.is_none() && !self.ended {
            let mut slot = None;
            if self.read_frame(&mut slot)? {
                self.next = slot;
            }
        }
        while self.next.as_ref().is_some_and(|n| n.time < time) {
            let mut spare = self.prev.take();
            if self.read_frame(&mut spare)? {
                self.prev = std::mem::replace(&mut self.next, spare);
            } else {
                self.prev = self.next.take();
                break;
            }
        }
        let d =
            |f: &Option<DecodedFrame>| f.as_ref().map_or(f64::INFINITY, |f| (f.time - time).abs());
        let (dp, dn) = (d(&self.prev), d(&self.next));
        let best = if dp <= dn { &self.prev } else { &self.next };
        match best {
            Some(f) if dp.min(dn) < tolerance => Ok(Ok(f)),
            Some(f) => Ok(Err(format!(
                "at {:.6} s, {:.6} s away",
                f.time,
                (f.time - time).abs()
            ))),
            None => Ok(Err(
                "none: the decoder returned no frame from there on".into()
            )),
        }
    }

    /// The time of the next frame not yet passed (`None` at the end).
    fn position(&self) -> Option<f64> {
        self.next.as_ref().map(|f| f.time)
    }
}

impl Drop for VideoStream {
    fn drop(&mut self) {
        if !self.ended {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

// ------------------------------------------------------------------------ images

/// Decode one encoded camera image (PNG, JPEG) into `out` as `height × width × 3` RGB, as
/// Pillow's `convert("RGB")` does for 8-bit images (grey replicated, alpha dropped);
/// returns `(height, width)`. Other pixel types are refused by name.
pub(crate) fn decode_image(
    bytes: &[u8],
    out: &mut Vec<u8>,
) -> std::result::Result<(usize, usize), String> {
    use image::ColorType;
    let img =
        image::load_from_memory(bytes).map_err(|e| format!("the image does not decode ({e})"))?;
    let rgb = match img.color() {
        ColorType::Rgb8 => img.into_rgb8(),
        ColorType::L8 | ColorType::La8 | ColorType::Rgba8 => img.to_rgb8(),
        c => {
            return Err(format!(
                "the image is {c:?}; 8-bit grey, RGB or RGBA images are read"
            ))
        }
    };
    let (w, h) = rgb.dimensions();
    out.clear();
    out.extend_from_slice(rgb.as_raw());
    Ok((h as usize, w as usize))
}

/// One image feature's column of one data file.
struct ImageColumn {
    path: PathBuf,
    key: String,
    /// `(episode_index, frame_index)` → (batch, row).
    rows: std::collections::HashMap<(i64, i64), (usize, usize)>,
    /// Per batch: the feature's struct column.
    columns: Vec<arrow_array::ArrayRef>,
    frame: DecodedFrame,
}

impl ImageColumn {
    /// Read `key`'s column (a struct with a binary `bytes` field, Hugging Face's `Image`)
    /// and the row keys of the data file `path`.
    fn read(path: &Path, key: &str) -> Result<Self> {
        let mut rows = std::collections::HashMap::new();
        let mut columns = Vec::new();
        let expected = "an image: struct<bytes: binary, path: string>";
        for (i, b) in read_parquet_columns(path, Some(&["episode_index", "frame_index", key]))?
            .into_iter()
            .enumerate()
        {
            let ep = int_column(&b, path, "episode_index")?;
            let frame = int_column(&b, path, "frame_index")?;
            let col = column(&b, path, key)?.clone();
            let bytes_type = match col.data_type() {
                DataType::Struct(fields) => fields
                    .iter()
                    .find(|f| f.name() == "bytes")
                    .map(|f| f.data_type().clone()),
                _ => None,
            };
            if !matches!(
                bytes_type,
                Some(DataType::Binary) | Some(DataType::LargeBinary)
            ) {
                return Err(type_error(path, key, expected, col.data_type()));
            }
            for (r, (e, f)) in ep.iter().zip(&frame).enumerate() {
                rows.insert((*e, *f), (i, r));
            }
            columns.push(col);
        }
        Ok(ImageColumn {
            path: path.to_path_buf(),
            key: key.to_string(),
            rows,
            columns,
            frame: DecodedFrame {
                time: 0.0,
                hw: (0, 0),
                rgb: Vec::new(),
            },
        })
    }

    /// The encoded bytes at `(batch, row)` (`None` when null).
    fn bytes(&self, batch: usize, row: usize) -> Option<&[u8]> {
        let s = self.columns[batch].as_struct();
        if s.is_null(row) {
            return None;
        }
        let b = s.column_by_name("bytes")?;
        if b.is_null(row) {
            return None;
        }
        match b.data_type() {
            DataType::Binary => Some(b.as_binary::<i32>().value(row)),
            DataType::LargeBinary => Some(b.as_binary::<i64>().value(row)),
            _ => None,
        }
    }
}

/// One camera view's frames across episodes and files. A video feature: keeps one
/// [`VideoStream`] open and starts a new one when another file or an earlier time is asked
/// for. An image feature: keeps the camera's column of one data file and decodes the
/// frame's image (see the module docs).
pub struct FrameReader {
    program: PathBuf,
    tolerance: f64,
    stream: Option<VideoStream>,
    last: f64,
    images: Option<ImageColumn>,
}

impl std::fmt::Debug for FrameReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameReader")
            .field("program", &self.program)
            .field("tolerance", &self.tolerance)
            .field("stream", &self.stream)
            .field("images", &self.images.as_ref().map(|c| (&c.path, &c.key)))
            .finish()
    }
}

impl FrameReader {
    /// A reader decoding with `program` (see [`ffmpeg_program`]) at `tolerance` s.
    pub fn new(program: PathBuf, tolerance: f64) -> Self {
        FrameReader {
            program,
            tolerance,
            stream: None,
            last: f64::NEG_INFINITY,
            images: None,
        }
    }

    /// Frame `frame` of `episode` of the image feature `key`.
    fn image_frame(
        &mut self,
        data: &VideoDataset,
        key: &str,
        episode: &VideoEpisode,
        frame: usize,
    ) -> Result<&DecodedFrame> {
        let path = data.data_file(episode);
        if self
            .images
            .as_ref()
            .is_none_or(|c| c.path != path || c.key != key)
        {
            self.images = None;
            self.images = Some(ImageColumn::read(&path, key)?);
        }
        let col = self.images.as_mut().expect("read above");
        let fail = |reason: String| Error::ImageFrame {
            path: path.clone(),
            key: key.to_string(),
            episode: episode.episode_index,
            frame,
            reason,
        };
        let &(b, r) = col
            .rows
            .get(&(episode.episode_index, frame as i64))
            .ok_or_else(|| fail("the data file has no row for it".into()))?;
        let mut rgb = std::mem::take(&mut col.frame.rgb);
        let bytes = col.bytes(b, r).ok_or_else(|| {
            fail("its image has no `bytes` (an image stored only by path is not read)".into())
        })?;
        let hw = decode_image(bytes, &mut rgb).map_err(fail)?;
        col.frame = DecodedFrame {
            time: episode.timestamps[frame],
            hw,
            rgb,
        };
        Ok(&col.frame)
    }

    /// Frame `frame` of `episode` of view `key` of `data`: from its video (one
    /// [`Error::VideoFrame`] naming the file, the episode and the frame when the video has
    /// no frame there), or, for an image feature, decoded from the data file (one
    /// [`Error::ImageFrame`] naming the file, the camera, the episode and the frame when it
    /// cannot be read).
    pub fn frame(
        &mut self,
        data: &VideoDataset,
        key: &str,
        episode: &VideoEpisode,
        frame: usize,
    ) -> Result<&DecodedFrame> {
        if data.is_image(key) {
            return self.image_frame(data, key, episode, frame);
        }
        let path = data.video_file(key, episode)?;
        let span = episode.videos[key];
        let time = span.from_timestamp + episode.timestamps[frame];
        let reopen = match &self.stream {
            None => true,
            Some(s) => {
                s.path() != path
                    || time < self.last
                    || s.position().is_some_and(|p| time > p + MAX_READ_AHEAD_S)
            }
        };
        if reopen {
            self.stream = None;
            self.stream = Some(VideoStream::open(&self.program, &path, time)?);
        }
        self.last = time;
        let tolerance = self.tolerance;
        let stream = self.stream.as_mut().expect("opened above");
        match stream.frame_at(time, tolerance)? {
            Ok(f) => Ok(f),
            Err(nearest) => Err(Error::VideoFrame {
                path,
                episode: episode.episode_index,
                frame,
                timestamp: time,
                nearest,
                tolerance,
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/lerobot_video")
    }

    /// The committed fixture (LeRobot's layout, written with pyarrow + PyAV by
    /// `tests/fixtures/make_lerobot_video.py`): the frame index, without decoding.
    #[test]
    fn the_frame_index_of_a_lerobot_dataset_with_videos() {
        let d = VideoDataset::open(&fixture()).unwrap();
        assert_eq!(d.fps, 10.0);
        assert_eq!(
            d.video_keys,
            ["observation.images.front", "observation.images.wrist"]
        );
        assert_eq!(d.total_frames(), 12);
        assert_eq!(d.episodes.len(), 2);
        let e1 = &d.episodes[1];
        assert_eq!((e1.episode_index, e1.len()), (1, 7));
        assert_eq!(e1.timestamps[3], f64::from(0.3f32));
        assert_eq!(d.task(e1, 0), "Put the ball in the bowl!");
        assert_eq!(d.task(&d.episodes[0], 4), "pick the cube");
        let span = e1.videos["observation.images.wrist"];
        assert_eq!((span.chunk_index, span.file_index), (0, 0));
        assert_eq!(span.from_timestamp, 0.5);
        assert_eq!(
            d.video_file("observation.images.front", e1).unwrap(),
            fixture().join("videos/observation.images.front/chunk-000/file-000.mp4")
        );
        let e = d
            .check_views(&["observation.state".to_string()])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("observation.state") && e.contains("observation.images.front"),
            "{e}"
        );
        // The state-only reader reads the same dataset (its videos are not features it reads).
        let sel = super::super::FeatureSelection {
            fast: vec!["observation.state".into()],
            slow: Vec::new(),
            action: "action".into(),
        };
        let ds = super::super::read_selected(&fixture(), &sel).unwrap();
        assert_eq!(ds.total_frames(), 12);
    }

    /// PNG round trip (RGB exact; grey replicated, alpha dropped, as Pillow's
    /// `convert("RGB")`), and the refusals: bytes that are no image, a 16-bit image.
    #[test]
    fn camera_images_decode_to_rgb_like_pillow_or_are_refused_by_name() {
        use image::ImageEncoder;
        let png = |raw: &[u8], w: u32, h: u32, c: image::ColorType| {
            let mut v = Vec::new();
            image::codecs::png::PngEncoder::new(&mut v)
                .write_image(raw, w, h, c)
                .unwrap();
            v
        };
        let rgb: Vec<u8> = (0..2 * 3 * 3).map(|i| (i * 13) as u8).collect();
        let mut out = Vec::new();
        let hw = decode_image(&png(&rgb, 3, 2, image::ColorType::Rgb8), &mut out).unwrap();
        assert_eq!((hw, &out), ((2, 3), &rgb));
        let grey = [7u8, 200];
        decode_image(&png(&grey, 2, 1, image::ColorType::L8), &mut out).unwrap();
        assert_eq!(out, [7, 7, 7, 200, 200, 200]);
        let rgba = [1u8, 2, 3, 0, 4, 5, 6, 255];
        decode_image(&png(&rgba, 2, 1, image::ColorType::Rgba8), &mut out).unwrap();
        assert_eq!(out, [1, 2, 3, 4, 5, 6]);
        let e = decode_image(b"\x89PNG not really", &mut out).unwrap_err();
        assert!(e.contains("does not decode"), "{e}");
        let wide = [0u8, 1, 2, 3];
        let e = decode_image(&png(&wide, 2, 1, image::ColorType::L16), &mut out).unwrap_err();
        assert!(e.contains("L16") && e.contains("8-bit"), "{e}");
    }

    #[test]
    fn ffmpeg_versions_are_read_from_the_version_line() {
        assert_eq!(
            ffmpeg_version("ffmpeg version 5.1.9-0+deb12u1 Copyright (c) 2000-2026"),
            Some((5, 1))
        );
        assert_eq!(
            ffmpeg_version("ffmpeg version n7.1 Copyright"),
            Some((7, 1))
        );
        assert_eq!(
            ffmpeg_version("ffmpeg version 4.4.2-0ubuntu0.22.04.1"),
            Some((4, 4))
        );
        assert_eq!(
            ffmpeg_version("ffmpeg version N-113441-g8b3d2b9 Copyright"),
            None
        );
    }

    #[test]
    fn showinfo_lines_give_the_time_base_and_each_frames_time_and_size() {
        let tb = "[Parsed_showinfo_0 @ 0x5561] config in time_base: 1/10240, frame_rate: 10/1";
        assert_eq!(
            parse_showinfo(tb, None),
            Some(Ok(ShowInfo::TimeBase((1, 10240))))
        );
        let fr = "[Parsed_showinfo_0 @ 0x5561] n:   3 pts:   3072 pts_time:0.3     pos:  \
                  290 fmt:yuv420p sar:1/1 s:32x24 i:P iskey:0 type:P checksum:669F32E2";
        assert_eq!(
            parse_showinfo(fr, Some((1, 10240))),
            Some(Ok(ShowInfo::Frame(FrameInfo {
                time: 0.3,
                hw: (24, 32)
            })))
        );
        // A frame before any time base, a missing pts, other lines.
        assert!(matches!(parse_showinfo(fr, None), Some(Err(_))));
        let nopts = fr.replace("pts:   3072", "pts:NOPTS");
        assert!(matches!(
            parse_showinfo(&nopts, Some((1, 25))),
            Some(Err(_))
        ));
        let color = "[Parsed_showinfo_0 @ 0x5561] color_range:tv color_space:unknown";
        assert_eq!(parse_showinfo(color, Some((1, 25))), None);
        assert_eq!(parse_showinfo("Input #0, mov,mp4", None), None);
        // Exact for long files: pts 1_228_800_000 at 1/10240 is 120000 s.
        let long = fr.replace("pts:   3072", "pts:1228800000");
        match parse_showinfo(&long, Some((1, 10240))) {
            Some(Ok(ShowInfo::Frame(f))) => assert_eq!(f.time, 120000.0),
            other => panic!("{other:?}"),
        }
    }
}
