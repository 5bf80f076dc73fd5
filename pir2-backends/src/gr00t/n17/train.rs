//! πR² fine-tuning of GR00T N1.7's action head ([`Gr00tN17Head`]) with candle, on the
//! head's device (the CPU; a GPU with the `cuda` / `metal` features, see
//! [`crate::candle::device`]).
//!
//! The network is the inference head itself, loaded with [`Gr00tN17Head::load_trainable`]:
//! its projectors, position embedding, DiT and decoder are candle `Var`s, the backbone
//! post-processing (`vlln`, VL self-attention) stays frozen with the backbone, and a
//! zero-initialised delay table `e(d_vis)` is added to the action tokens. The draws and the
//! resumable machinery are the trainer's own ([`crate::train::Trainer`]): the same [`TrainConfig`]
//! (AdamW, cosine LR with warm-up, grad-norm clip, seed), the same batch sampler, step
//! checkpoints with the full training state, `interrupted-*` states, bit-identical resume.
//!
//! Each sample (the paper's robot recipe on GR00T's data pipeline): a frame `t` uniformly
//! over the frames whose whole chunk lies inside their episode (`t ≤ len − H`, as GR00T's
//! `ShardedSingleStepDataset` samples; an episode shorter than `H` gives none); the state
//! history ending at `t` (clamped at the episode start); the action chunk `a_{t..t+H}`
//! (encoded per sample by an [`ActionTargets`] when the targets depend on the sample, as
//! relative actions do); `τ`/mask from the schedule's draw (πR²: staircase with a clean,
//! masked front of `d ~ U{1..d_max}`, or the warm-up branch); `d_vis ~ U{0..d_vis_max}` per sample, the VL
//! tokens of frame `max(0, t − d_vis)` and `e(d_vis)` on the action tokens. GR00T's discrete
//! timesteps are [`timestep_bucket`]`(τ_p)` per action token and `state_timestep` for the
//! state token (per-token AdaLN, as deployed). Actions are padded with zeros to `A_max`; the
//! loss is the trainer's masked MSE over the robot's `A` action dimensions only.
//!
//! The backbone is frozen, so its tokens are computed once per frame: a [`VlCache`] holds
//! them (after `vlln` and the VL self-attention, which are frozen too) in one file keyed by
//! a digest of everything they depend on ([`vl_cache_key`]); another input gets another
//! file, never a stale one. [`PrecomputedFeatures`] reads backbone outputs a user computed
//! with the real backbone.
//!
//! The training forward is [`Gr00tN17Head::velocity_train`]: GR00T's dropout in the DiT
//! blocks at the checkpoint's rate (`diffusion_model_cfg.dropout`, `final_dropout`; see
//! [`DitDropout`]), masks keyed by the run's seed and the step index, so a resumed run is
//! bit-identical to an uninterrupted one. [`Gr00tTrainer::dropout`]`(false)` trains without
//! it. Whether it is on, and its rate, are part of the run's identity ([`RUN_FILE`]).
//!
//! The per-step tensors live on the head's device (`load_trainable(.., device)`); the
//! optimiser state and update are on the host. Only the CPU has been run; the `cuda` and
//! `metal` features have not been compiled here.
//!
//! Not done here: EMA, self-rollout and validation hooks of [`crate::train::Trainer`] are refused
//! by name.

use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom};

use candle_core::{DType, Var};
use sha2::{Digest, Sha256};

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use candle_core::Tensor;

use crate::config::{SlowSpec, Spec, Stats};
use crate::error::{Error, Result};
use crate::gr00t::n17::{
    is_trained, timestep_bucket, DitDropout, Gr00tN17Head, TensorIndex, Timesteps, VlTokens,
};
use crate::train::*;

/// The embodiment as the trainer sees it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Gr00tTrainSpec {
    /// Chunk length `H`.
    pub horizon: usize,
    /// The robot's action width `A` (≤ the head's `max_action_dim`); the data's actions.
    pub action_dim: usize,
    /// Largest slow-feature age drawn (the delay table has `d_vis_max + 1` rows).
    pub d_vis_max: usize,
    /// The embodiment slot of the category-specific layers.
    pub embodiment_id: u32,
    /// GR00T timestep of the state token (deployment default: `buckets − 1`).
    pub state_timestep: u32,
}

/// How a sample's action chunk becomes the model's training target when the target depends
/// on the sample, not only on the frame: GR00T's relative action groups are `a − s`, with `s`
/// the newest raw state of the sample's observation window (frame `t` itself), normalised
/// with per-chunk-slot statistics. Without one, the trainer reads the data's actions as
/// already normalised.
pub trait ActionTargets {
    /// Encode in place `chunk` (`[H, A]`): the raw actions of episode `episode` from frame
    /// `frame` on (slot `p` holds frame `frame + p`; the trainer draws only chunks inside the
    /// episode), the sample's observation window ending at `frame`.
    fn encode(&self, episode: usize, frame: usize, chunk: &mut [f32]) -> Result<()>;
}

// ---------------------------------------------------------------- VL features

/// Per-frame VL tokens, indexed by the global frame index (episodes in order).
pub trait VlFeatures {
    /// Frames.
    fn frames(&self) -> usize;
    /// Tokens `T` per frame.
    fn tokens(&self) -> usize;
    /// Token width `D_vl`.
    fn dim(&self) -> usize;
    /// Frame `frame`: `emb [T·D]`, `image_mask [T]`, `attention_mask [T]` (1 = set).
    fn read(
        &mut self,
        frame: usize,
        emb: &mut [f32],
        image_mask: &mut [f32],
        attention_mask: &mut [f32],
    ) -> Result<()>;
}

/// Backbone outputs computed elsewhere, one safetensors file: `embeddings [N, T, D_vl]`
/// (F32/BF16/F16, the backbone's last hidden states before `vlln`), `image_mask [N, T]`
/// and optionally `attention_mask [N, T]` (any integer, bool or float type; nonzero = set;
/// absent = every token attended), `N` = the dataset's frames in episode order. Rows are
/// read one chunk at a time, never the whole file.
#[derive(Debug)]
pub struct PrecomputedFeatures {
    index: TensorIndex,
    path: PathBuf,
    frames: usize,
    tokens: usize,
    dim: usize,
    attention: bool,
}

impl PrecomputedFeatures {
    /// Open `path` and check its tensors (an error names the file and the tensor).
    pub fn open(path: &Path) -> Result<Self> {
        let index = TensorIndex::open(path, "")?;
        let bad = |name: &str, expected: Vec<usize>, got: &[usize]| Error::TensorShape {
            path: path.to_path_buf(),
            name: name.to_string(),
            expected,
            got: got.to_vec(),
        };
        let missing = |name: &str| Error::MissingTensor {
            path: path.to_path_buf(),
            name: name.to_string(),
        };
        let (frames, tokens, dim) = match index.shape("embeddings") {
            Some(&[n, t, d]) if n > 0 && t > 0 && d > 0 => (n, t, d),
            Some(s) => return Err(bad("embeddings", vec![1, 1, 1], s)),
            None => return Err(missing("embeddings")),
        };
        match index.shape("image_mask") {
            Some(s) if s == [frames, tokens] => {}
            Some(s) => return Err(bad("image_mask", vec![frames, tokens], s)),
            None => return Err(missing("image_mask")),
        }
        let attention = match index.shape("attention_mask") {
            Some(s) if s == [frames, tokens] => true,
            Some(s) => return Err(bad("attention_mask", vec![frames, tokens], s)),
            None => false,
        };
        Ok(Self {
            index,
            path: path.to_path_buf(),
            frames,
            tokens,
            dim,
            attention,
        })
    }

    /// Frames `N`.
    pub fn frames(&self) -> usize {
        self.frames
    }
    /// Tokens `T` per frame.
    pub fn tokens(&self) -> usize {
        self.tokens
    }
    /// Token width `D_vl`.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// A digest of the file: its size, modification time and safetensors header (not every
    /// byte: a rewrite in place that keeps both size and time is not detected).
    pub fn fingerprint(&self) -> Result<String> {
        let meta = std::fs::metadata(&self.path).map_err(|e| Error::io(&self.path, e))?;
        let mtime = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos());
        let mut f = File::open(&self.path).map_err(|e| Error::io(&self.path, e))?;
        let mut len = [0u8; 8];
        f.read_exact(&mut len)
            .map_err(|e| Error::io(&self.path, e))?;
        let n = u64::from_le_bytes(len).min(meta.len());
        let mut header = vec![0u8; n as usize];
        f.read_exact(&mut header)
            .map_err(|e| Error::io(&self.path, e))?;
        let mut h = Sha256::new();
        h.update(meta.len().to_le_bytes());
        h.update(mtime.to_le_bytes());
        h.update(&header);
        Ok(hex(&h.finalize()))
    }

    /// Rows `first .. first + count`: embeddings, image mask, attention mask.
    fn rows(&self, first: usize, count: usize) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        let emb = self.index.read_rows("embeddings", first, count)?;
        let image = self.index.read_rows("image_mask", first, count)?;
        let attn = if self.attention {
            self.index.read_rows("attention_mask", first, count)?
        } else {
            vec![1.0; count * self.tokens]
        };
        Ok((emb, image, attn))
    }
}

/// A SHA-256 over every file under `root/dir` for each of `dirs` (relative path and
/// contents, in sorted order; a missing directory counts as empty): e.g. a LeRobot
/// dataset's `meta` and `data`.
pub fn tree_fingerprint(root: &Path, dirs: &[&str]) -> Result<String> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
        let rd = match std::fs::read_dir(dir) {
            Ok(rd) => rd,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(Error::io(dir, e)),
        };
        for e in rd {
            let p = e.map_err(|e| Error::io(dir, e))?.path();
            if p.is_dir() {
                walk(&p, out)?;
            } else {
                out.push(p);
            }
        }
        Ok(())
    }
    let mut files = Vec::new();
    for d in dirs {
        walk(&root.join(d), &mut files)?;
    }
    files.sort();
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    for f in files {
        let rel = f.strip_prefix(root).unwrap_or(&f);
        h.update(rel.to_string_lossy().as_bytes());
        h.update([0]);
        let mut file = File::open(&f).map_err(|e| Error::io(&f, e))?;
        loop {
            let n = file.read(&mut buf).map_err(|e| Error::io(&f, e))?;
            if n == 0 {
                break;
            }
            h.update(&buf[..n]);
        }
        h.update([0]);
    }
    Ok(hex(&h.finalize()))
}

/// A SHA-256 over every parameter of `head` (names and `f32` bits) and its configuration:
/// identifies the checkpoint a run started from.
pub fn head_fingerprint(head: &Gr00tN17Head) -> Result<String> {
    let mut h = Sha256::new();
    h.update(format!("{:?}", head.config()).as_bytes());
    for (name, t) in head.parameters() {
        h.update(name.as_bytes());
        for v in t.flatten_all()?.to_vec1::<f32>()? {
            h.update(v.to_le_bytes());
        }
    }
    Ok(hex(&h.finalize()))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The key of the VL-token cache: a SHA-256 over the dataset's and the backbone features'
/// digests (the caller's) and everything of the head that shapes the cached tokens (the
/// frozen `vlln` / VL self-attention tensors, bit for bit, and the configuration).
pub fn vl_cache_key(head: &Gr00tN17Head, dataset: &str, features: &str) -> Result<String> {
    let mut h = Sha256::new();
    h.update(b"pir2 gr00t vl cache v1\0");
    h.update(dataset.as_bytes());
    h.update([0]);
    h.update(features.as_bytes());
    h.update([0]);
    h.update(format!("{:?}", head.config()).as_bytes());
    for (name, t) in head.parameters() {
        let short = name.strip_prefix(crate::gr00t::n17::PREFIX).unwrap_or(name);
        if is_trained(short) {
            continue;
        }
        h.update(name.as_bytes());
        for v in t.flatten_all()?.to_vec1::<f32>()? {
            h.update(v.to_le_bytes());
        }
    }
    Ok(hex(&h.finalize()))
}

const CACHE_MAGIC: &[u8; 8] = b"PIR2VLC1";

/// The header of a cache file.
#[derive(Debug, Serialize, Deserialize, PartialEq)]
struct CacheHeader {
    key: String,
    frames: usize,
    tokens: usize,
    dim: usize,
}

/// The processed VL tokens of every frame, on disk: `vl-<key prefix>.bin` in the cache
/// directory, one fixed-size record per frame (`T·D` little-endian `f32`, then the image and
/// attention masks as `T` bytes each) after a header naming the full key. Written to a
/// temporary file and renamed, so a file under its name is always complete.
#[derive(Debug)]
pub struct VlCache {
    file: File,
    path: PathBuf,
    header: CacheHeader,
    start: u64,
    record: Vec<u8>,
}

impl VlCache {
    /// The cache file of `key` in `dir`.
    pub fn path_for(dir: &Path, key: &str) -> PathBuf {
        dir.join(format!("vl-{}.bin", &key[..key.len().min(32)]))
    }

    /// Open the cache of `key` in `dir`, or build it first by running the frozen head's
    /// backbone post-processing over every frame of `features`. Returns the cache and
    /// whether it was built now.
    pub fn open_or_build(
        dir: &Path,
        key: &str,
        head: &Gr00tN17Head,
        features: &PrecomputedFeatures,
    ) -> Result<(Self, bool)> {
        let path = Self::path_for(dir, key);
        let header = CacheHeader {
            key: key.to_string(),
            frames: features.frames,
            tokens: features.tokens,
            dim: features.dim,
        };
        if path.is_file() {
            return Ok((Self::open(&path, &header)?, false));
        }
        if features.dim != head.config().backbone_embedding_dim {
            return Err(Error::TensorShape {
                path: features.path.clone(),
                name: "embeddings".into(),
                expected: vec![
                    features.frames,
                    features.tokens,
                    head.config().backbone_embedding_dim,
                ],
                got: vec![features.frames, features.tokens, features.dim],
            });
        }
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let tmp = dir.join(format!(".vl-build-{}", std::process::id()));
        {
            let f = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
            let mut w = BufWriter::new(f);
            let head_json = serde_json::to_vec(&header).map_err(|e| Error::Format {
                path: tmp.clone(),
                message: e.to_string(),
            })?;
            let io = |e| Error::io(&tmp, e);
            use std::io::Write;
            w.write_all(CACHE_MAGIC).map_err(io)?;
            w.write_all(&(head_json.len() as u64).to_le_bytes())
                .map_err(io)?;
            w.write_all(&head_json).map_err(io)?;
            let (t, d) = (features.tokens, features.dim);
            let chunk = 16;
            let mut first = 0;
            while first < features.frames {
                let count = chunk.min(features.frames - first);
                let (emb, image, attn) = features.rows(first, count)?;
                let x = Tensor::from_vec(emb, (count, t, d), head.device())?;
                let y = head.process_backbone(&x)?.flatten_all()?.to_vec1::<f32>()?;
                for i in 0..count {
                    for v in &y[i * t * d..(i + 1) * t * d] {
                        w.write_all(&v.to_le_bytes()).map_err(io)?;
                    }
                    for m in [&image, &attn] {
                        let bytes: Vec<u8> = m[i * t..(i + 1) * t]
                            .iter()
                            .map(|&v| u8::from(v != 0.0))
                            .collect();
                        w.write_all(&bytes).map_err(io)?;
                    }
                }
                first += count;
            }
            let f = w
                .into_inner()
                .map_err(|e| Error::io(&tmp, e.into_error()))?;
            f.sync_all().map_err(io)?;
        }
        std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))?;
        Ok((Self::open(&path, &header)?, true))
    }

    fn open(path: &Path, want: &CacheHeader) -> Result<Self> {
        let bad = |message: String| Error::Format {
            path: path.to_path_buf(),
            message,
        };
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut magic = [0u8; 16];
        file.read_exact(&mut magic)
            .map_err(|_| bad("not a pir2 VL cache (too short)".into()))?;
        if &magic[..8] != CACHE_MAGIC {
            return Err(bad("not a pir2 VL cache".into()));
        }
        let n = u64::from_le_bytes(magic[8..16].try_into().unwrap_or_default());
        if n > 1 << 20 || 16 + n > len {
            return Err(bad(format!("header length {n} does not fit the file")));
        }
        let mut text = vec![0u8; n as usize];
        file.read_exact(&mut text).map_err(|e| Error::io(path, e))?;
        let header: CacheHeader =
            serde_json::from_slice(&text).map_err(|e| bad(format!("header: {e}")))?;
        if header != *want {
            return Err(bad(format!(
                "written for {header:?}, this run needs {want:?}; remove the file"
            )));
        }
        let record = header.tokens * header.dim * 4 + 2 * header.tokens;
        let start = 16 + n;
        if len != start + (header.frames * record) as u64 {
            return Err(bad(format!(
                "{len} bytes; {} frames of {record} bytes need {}",
                header.frames,
                start + (header.frames * record) as u64
            )));
        }
        Ok(Self {
            file,
            path: path.to_path_buf(),
            header,
            start,
            record: vec![0; record],
        })
    }

    /// The cache file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl VlFeatures for VlCache {
    fn frames(&self) -> usize {
        self.header.frames
    }
    fn tokens(&self) -> usize {
        self.header.tokens
    }
    fn dim(&self) -> usize {
        self.header.dim
    }
    fn read(
        &mut self,
        frame: usize,
        emb: &mut [f32],
        image_mask: &mut [f32],
        attention_mask: &mut [f32],
    ) -> Result<()> {
        let (t, d) = (self.header.tokens, self.header.dim);
        if frame >= self.header.frames {
            return Err(Error::shape(
                "VL cache frame",
                format!("< {}", self.header.frames),
                frame,
            ));
        }
        let pos = self.start + (frame * self.record.len()) as u64;
        self.file
            .seek(SeekFrom::Start(pos))
            .and_then(|_| self.file.read_exact(&mut self.record))
            .map_err(|e| Error::io(&self.path, e))?;
        for (o, c) in emb[..t * d].iter_mut().zip(self.record.chunks_exact(4)) {
            *o = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
        let masks = &self.record[t * d * 4..];
        for (o, &m) in image_mask[..t].iter_mut().zip(&masks[..t]) {
            *o = f32::from(m);
        }
        for (o, &m) in attention_mask[..t].iter_mut().zip(&masks[t..2 * t]) {
            *o = f32::from(m);
        }
        Ok(())
    }
}

// ---------------------------------------------------------------- trainer

/// The run's identity file in the output directory: a resumed run must match it.
pub const RUN_FILE: &str = "gr00t_run.json";
/// The head's weights in every step checkpoint (GR00T's names, with the delay table).
pub const WEIGHTS_FILE: &str = "model.safetensors";

/// Builder and runner of one πR² fine-tuning run of a [`Gr00tN17Head`].
pub struct Gr00tTrainer<'a> {
    cfg: TrainConfig,
    spec: Gr00tTrainSpec,
    out_dir: PathBuf,
    ctl: RunControl<'a>,
    identity: serde_json::Value,
    extra_files: Vec<(String, Vec<u8>)>,
    targets: Option<&'a dyn ActionTargets>,
    dropout: bool,
}

impl std::fmt::Debug for Gr00tTrainer<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gr00tTrainer")
            .field("cfg", &self.cfg)
            .field("spec", &self.spec)
            .field("out_dir", &self.out_dir)
            .field("resume", &self.ctl.resume)
            .field("dropout", &self.dropout)
            .finish_non_exhaustive()
    }
}

impl<'a> Gr00tTrainer<'a> {
    /// A run with hyper-parameters `cfg` for `spec`, writing to `out_dir` (step checkpoints
    /// `step-NNNNNN/`, `loss.jsonl`, [`RUN_FILE`]).
    pub fn new(cfg: TrainConfig, spec: Gr00tTrainSpec, out_dir: impl AsRef<Path>) -> Self {
        Self {
            cfg,
            spec,
            out_dir: out_dir.as_ref().to_path_buf(),
            ctl: RunControl::default(),
            identity: serde_json::Value::Null,
            extra_files: Vec::new(),
            targets: None,
            dropout: true,
        }
    }
    /// Apply GR00T's DiT dropout at the checkpoint's rate in the training forward (on by
    /// default; see [`DitDropout`]).
    pub fn dropout(mut self, on: bool) -> Self {
        self.dropout = on;
        self
    }
    /// Encode every sample's chunk with `targets` (the data then holds raw actions); without
    /// it the data's actions are the normalised targets themselves.
    pub fn action_targets(mut self, targets: &'a dyn ActionTargets) -> Self {
        self.targets = Some(targets);
        self
    }
    run_controls!();
    /// What the run is made of (inputs' digests, embodiment…), written to [`RUN_FILE`] with
    /// the spec; a resumed run whose identity differs is refused, naming the file.
    pub fn identity(mut self, id: serde_json::Value) -> Self {
        self.identity = id;
        self
    }
    /// A file written into every step checkpoint next to the weights (e.g. `config.json`).
    pub fn checkpoint_file(mut self, name: &str, bytes: Vec<u8>) -> Self {
        self.extra_files.push((name.to_string(), bytes));
        self
    }

    fn check(&self, head: &Gr00tN17Head, data: &[Episode], vl: &dyn VlFeatures) -> Result<Spec> {
        let cfg = &self.cfg;
        let s = &self.spec;
        let c = head.config();
        if cfg.ema.is_some() || cfg.self_rollout.is_some() {
            return Err(Error::config(
                "train.ema/self_rollout",
                "not supported by the GR00T trainer",
            ));
        }
        if head.trainable_vars().is_empty() {
            return Err(Error::config(
                "gr00t head",
                "loaded for inference; use Gr00tN17Head::load_trainable",
            ));
        }
        match head.delay_embedding().map(|t| t.dim(0)).transpose()? {
            Some(rows) if rows == s.d_vis_max + 1 => {}
            other => {
                return Err(Error::config(
                    "gr00t d_vis_max",
                    format!(
                        "the head's delay table has {other:?} rows, d_vis_max = {} needs {}",
                        s.d_vis_max,
                        s.d_vis_max + 1
                    ),
                ))
            }
        }
        if s.action_dim == 0 || s.action_dim > c.max_action_dim {
            return Err(Error::config(
                "gr00t action_dim",
                format!(
                    "{} must be in 1..={} (max_action_dim)",
                    s.action_dim, c.max_action_dim
                ),
            ));
        }
        if c.add_pos_embed && s.horizon > c.max_seq_len {
            return Err(Error::config(
                "gr00t horizon",
                format!(
                    "{} is above the position embedding's {} rows",
                    s.horizon, c.max_seq_len
                ),
            ));
        }
        if s.embodiment_id as usize >= c.max_num_embodiments {
            return Err(Error::config(
                "gr00t embodiment_id",
                format!(
                    "{} is not a slot in 0..{}",
                    s.embodiment_id, c.max_num_embodiments
                ),
            ));
        }
        if s.state_timestep as usize >= c.num_timestep_buckets {
            return Err(Error::config(
                "gr00t state_timestep",
                format!("{} outside 0..{}", s.state_timestep, c.num_timestep_buckets),
            ));
        }
        let frames: usize = data.iter().map(Episode::len).sum();
        let full: usize = data
            .iter()
            .map(|e| (e.len() + 1).saturating_sub(s.horizon))
            .sum();
        if full == 0 {
            let longest = data.iter().map(Episode::len).max().unwrap_or(0);
            return Err(Error::Dataset(format!(
                "no episode holds one whole action chunk of H = {} frames (the longest has \
                 {longest}); GR00T trains only on chunks inside an episode",
                s.horizon
            )));
        }
        if vl.frames() != frames || vl.dim() != c.backbone_embedding_dim {
            return Err(Error::Dataset(format!(
                "the VL features hold {} frames of width {}, the dataset has {frames} frames and \
                 the head wants width {}",
                vl.frames(),
                vl.dim(),
                c.backbone_embedding_dim
            )));
        }
        let spec = Spec {
            horizon: s.horizon,
            action_dim: s.action_dim,
            n_obs: c.state_history_length,
            fast_dim: c.max_state_dim,
            slow: SlowSpec::None,
            d_vis_max: s.d_vis_max,
        };
        spec.validate()?;
        cfg.validate(spec.horizon)?;
        check_dataset(data, &spec)?;
        Ok(spec)
    }

    /// Train `head` (loaded with [`Gr00tN17Head::load_trainable`]) on `data` (per frame the
    /// normalised state padded to `max_state_dim` as the fast row, the normalised action of
    /// width `A`, or the raw one with [`action_targets`](Self::action_targets)) with the VL tokens of `vl` (frame `i` = the `i`-th frame over the episodes in
    /// order). On return the head holds the last step's weights.
    pub fn run(
        mut self,
        head: &Gr00tN17Head,
        data: &[Episode],
        vl: &mut dyn VlFeatures,
    ) -> Result<TrainReport> {
        let spec = self.check(head, data, vl)?;
        let cfg = self.cfg.clone();
        let out = self.out_dir.clone();
        // The run's identity: written once, checked on resume.
        let dit = &head.config().dit;
        let dropout = (self.dropout && dit.dropout > 0.0).then(
            || serde_json::json!({ "rate": dit.dropout, "final_dropout": dit.final_dropout }),
        );
        let id = serde_json::json!({
            "spec": self.spec,
            "identity": self.identity,
            "dropout": dropout,
        });
        let id_path = out.join(RUN_FILE);
        let resume_from = self.ctl.prepare(&out)?;
        if resume_from.is_some() {
            let text = std::fs::read_to_string(&id_path).map_err(|e| Error::io(&id_path, e))?;
            let old: serde_json::Value =
                serde_json::from_str(&text).map_err(|e| Error::Format {
                    path: id_path.clone(),
                    message: e.to_string(),
                })?;
            if old != id {
                return Err(Error::config(
                    "train.resume",
                    format!(
                        "{} records another run ({old}); this one is {id}",
                        id_path.display()
                    ),
                ));
            }
        } else {
            let text = serde_json::to_string_pretty(&id).map_err(|e| Error::Format {
                path: id_path.clone(),
                message: e.to_string(),
            })?;
            let tmp = out.join(format!(".{RUN_FILE}.tmp"));
            crate::checkpoint::write_durable(&tmp, text.as_bytes())?;
            std::fs::rename(&tmp, &id_path).map_err(|e| Error::io(&id_path, e))?;
        }
        let mut log = LossLog::open(Some(&out), None)?;

        // The head's device: every per-step tensor lives there; the AdamW update runs on
        // the host copies, as in the U-Net trainer.
        let dev = head.device().clone();
        let vars: Vec<Var> = head
            .trainable_vars()
            .iter()
            .map(|(_, v)| v.clone())
            .collect();
        let names: Vec<String> = head
            .trainable_vars()
            .iter()
            .map(|(n, _)| n.clone())
            .collect();
        let params = vars
            .iter()
            .map(|v| Ok(v.as_tensor().flatten_all()?.to_vec1::<f32>()?))
            .collect::<Result<Vec<_>>>()?;
        let mut st = State {
            step: 0,
            opt: AdamW::new(&cfg, &params),
            ema: None,
            params,
            best: None,
            report: TrainReport::default(),
        };
        let stats = Stats::identity(&spec);
        let mut batcher = Batcher::new(data, &spec, &stats, &cfg);
        batcher.full_chunks_only(data);
        let set_vars = |params: &[Vec<f32>]| -> Result<()> {
            for (v, p) in vars.iter().zip(params) {
                v.set(&Tensor::from_slice(p, v.dims(), &dev)?)?;
            }
            Ok(())
        };
        if let Some(dir) = &resume_from {
            batcher.rng = st.load(dir, &cfg, &names)?;
            set_vars(&st.params)?;
        }
        let extra = std::mem::take(&mut self.extra_files);
        let write_model = |dir: &Path| -> Result<()> {
            head.save_weights(&dir.join(WEIGHTS_FILE))?;
            for (name, bytes) in &extra {
                crate::checkpoint::write_durable(&dir.join(name), bytes)?;
            }
            Ok(())
        };
        let c = head.config();
        let (b, h, a, a_max) = (
            cfg.batch_size,
            spec.horizon,
            spec.action_dim,
            c.max_action_dim,
        );
        let (t_vl, d_vl) = (vl.tokens(), vl.dim());
        let buckets = c.num_timestep_buckets;
        let cum: Vec<usize> = data
            .iter()
            .scan(0, |acc, e| {
                let start = *acc;
                *acc += e.len();
                Some(start)
            })
            .collect();
        let mut emb = vec![0f32; b * t_vl * d_vl];
        let mut image = vec![0f32; b * t_vl];
        let mut attn = vec![0f32; b * t_vl];
        let mut x_pad = vec![0f32; b * h * a_max];
        let mut t_act = vec![0u32; b * h];
        let mut t_tok = vec![0u32; b * (1 + h)];
        let mut grads: Vec<Vec<f32>> = st.params.iter().map(|p| vec![0.0; p.len()]).collect();
        let ids = Tensor::from_vec(vec![self.spec.embodiment_id; b], b, &dev)?;

        for step in st.step..cfg.steps {
            if self.ctl.stop_before(step, Some(&out), &mut log, |p| {
                st.save_step(write_model, p, batcher.rng.state(), &names, &cfg)
            })? {
                break;
            }
            let lr = cfg.lr_at(step);
            match self.targets {
                Some(tg) => {
                    let mut f = |e: usize, t: usize, c: &mut [f32]| tg.encode(e, t, c);
                    batcher.fill_encoded(data, Some(&mut f))?
                }
                None => batcher.fill(data)?,
            }
            for i in 0..b {
                let (e, t) = batcher.slow_frame[i];
                vl.read(
                    cum[e] + t,
                    &mut emb[i * t_vl * d_vl..(i + 1) * t_vl * d_vl],
                    &mut image[i * t_vl..(i + 1) * t_vl],
                    &mut attn[i * t_vl..(i + 1) * t_vl],
                )?;
                t_tok[i * (1 + h)] = self.spec.state_timestep;
                for p in 0..h {
                    let q = i * h + p;
                    let tb = timestep_bucket(batcher.tau[q], buckets);
                    t_act[q] = tb;
                    t_tok[i * (1 + h) + 1 + p] = tb;
                    x_pad[q * a_max..q * a_max + a].copy_from_slice(&batcher.x[q * a..(q + 1) * a]);
                }
            }
            let state = Tensor::from_slice(&batcher.fast, (b, spec.n_obs, spec.fast_dim), &dev)?;
            let x = Tensor::from_slice(&x_pad, (b, h, a_max), &dev)?;
            let ta = Tensor::from_slice(&t_act, (b, h), &dev)?;
            let tt = Tensor::from_slice(&t_tok, (b, 1 + h), &dev)?;
            let vl_emb = Tensor::from_slice(&emb, (b, t_vl, d_vl), &dev)?;
            let im = Tensor::from_slice(&image, (b, t_vl), &dev)?;
            let am = Tensor::from_slice(&attn, (b, t_vl), &dev)?;
            let dv = Tensor::from_slice(&batcher.dvis, b, &dev)?;
            let tokens = VlTokens {
                embeddings: &vl_emb,
                attention_mask: Some(&am),
                image_mask: Some(&im),
                d_vis: Some(&dv),
            };
            let s = head.encode_state(&state, &ids)?;
            let ts = Timesteps::PerPosition {
                actions: &ta,
                tokens: &tt,
            };
            let v = if dropout.is_some() {
                let d = DitDropout::from_config(&c.dit, cfg.seed, step as u64);
                head.velocity_train(&s, &x, ts, &tokens, &ids, &d)?
            } else {
                head.velocity(&s, &x, ts, &tokens, &ids)?
            };
            let loss = masked_mse(v.narrow(2, 0, a)?, &batcher.target, &batcher.mask)?;
            let loss_v = loss.to_dtype(DType::F32)?.to_scalar::<f32>()?;
            if !loss_v.is_finite() {
                return Err(Error::Diverged {
                    step: step + 1,
                    loss: loss_v,
                });
            }
            let gn = backward_to_host(&loss, &vars, cfg.grad_clip, &mut grads)?;
            st.opt.step(&mut st.params, &grads, lr);
            set_vars(&st.params)?;
            let done = step + 1;
            let progress = Progress {
                step: done,
                steps: cfg.steps,
                loss: loss_v,
                lr,
                grad_norm: gn,
            };
            if self.ctl.after_step(&cfg, &mut st, &mut log, progress)? {
                let dir = step_dir(&out, done);
                st.report.checkpoints.push(CheckpointRecord {
                    step: done,
                    score: None,
                    dir: Some(dir.clone()),
                });
                log.flush()?;
                st.save_step(write_model, &dir, batcher.rng.state(), &names, &cfg)?;
            }
        }
        finish(Some(&out), &mut log, st, &cfg)
    }
}
