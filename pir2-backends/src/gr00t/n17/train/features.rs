//! The frozen backbone's tokens as the trainer reads them ([`VlFeatures`]): backbone outputs
//! a user computed elsewhere ([`PrecomputedFeatures`]), or tokens computed once per frame and
//! kept in one file keyed by a digest of everything they depend on ([`VlCache`],
//! [`vl_cache_key`], built from [`head_fingerprint`] and [`tree_fingerprint`]).

use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use candle_core::Tensor;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::error::{Error, Result};
use crate::gr00t::n17::{is_trained, Gr00tN17Head, TensorIndex};

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
