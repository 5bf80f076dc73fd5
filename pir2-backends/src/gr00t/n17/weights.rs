//! Reading the action-head tensors of a checkpoint: one `*.safetensors` file or a sharded
//! checkpoint (`model.safetensors.index.json` + shards). Only the headers are parsed up
//! front; each tensor is read from its byte range when asked for, so the backbone's
//! gigabytes in the same shards are never loaded.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use serde_json::Value;

use crate::error::{Error, Result};

/// Name of a sharded checkpoint's index (Hugging Face's convention).
pub const INDEX_FILE: &str = "model.safetensors.index.json";
/// Name of an unsharded checkpoint's weights.
pub const SINGLE_FILE: &str = "model.safetensors";

#[derive(Debug, Clone)]
struct Entry {
    file: PathBuf,
    dtype: String,
    shape: Vec<usize>,
    /// Absolute byte range in `file`.
    start: u64,
    end: u64,
}

/// The tensors under one name prefix of a safetensors checkpoint, with where they live.
#[derive(Debug)]
pub struct TensorIndex {
    /// The file the user named (a `.safetensors`, an index, or the directory's file).
    source: PathBuf,
    entries: BTreeMap<String, Entry>,
}

fn st_err(path: &Path, message: impl Into<String>) -> Error {
    Error::Safetensors {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// The header of one safetensors file: `name → (dtype, shape, absolute byte range)`.
fn read_header(path: &Path) -> Result<BTreeMap<String, Entry>> {
    let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|_| st_err(path, "file too short for a safetensors header"))?;
    let n = u64::from_le_bytes(len);
    if n > 100_000_000 || 8 + n > file_len {
        return Err(st_err(
            path,
            format!("header length {n} does not fit the file"),
        ));
    }
    let mut header = vec![0u8; n as usize];
    f.read_exact(&mut header).map_err(|e| Error::io(path, e))?;
    let value: Value = serde_json::from_slice(&header)
        .map_err(|e| st_err(path, format!("header is not JSON: {e}")))?;
    let Value::Object(map) = value else {
        return Err(st_err(path, "header is not a JSON object"));
    };
    let base = 8 + n;
    let mut out = BTreeMap::new();
    for (name, v) in map {
        if name == "__metadata__" {
            continue;
        }
        let bad = |what: &str| st_err(path, format!("tensor `{name}`: {what}"));
        let dtype = v
            .get("dtype")
            .and_then(Value::as_str)
            .ok_or_else(|| bad("no dtype"))?
            .to_string();
        let shape = v
            .get("shape")
            .and_then(Value::as_array)
            .ok_or_else(|| bad("no shape"))?
            .iter()
            .map(|d| d.as_u64().map(|d| d as usize))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| bad("shape is not a list of integers"))?;
        let offs = v
            .get("data_offsets")
            .and_then(Value::as_array)
            .and_then(|a| {
                let s = a.first()?.as_u64()?;
                let e = a.get(1)?.as_u64()?;
                Some((s, e))
            })
            .ok_or_else(|| bad("no data_offsets"))?;
        if offs.0 > offs.1 || base + offs.1 > file_len {
            return Err(bad("data_offsets outside the file"));
        }
        out.insert(
            name.clone(),
            Entry {
                file: path.to_path_buf(),
                dtype,
                shape,
                start: base + offs.0,
                end: base + offs.1,
            },
        );
    }
    Ok(out)
}

impl TensorIndex {
    /// Index the tensors whose names start with `prefix` in `path`: a directory (its
    /// `model.safetensors.index.json`, else its `model.safetensors`), an index file, or one
    /// `.safetensors` file.
    pub fn open(path: &Path, prefix: &str) -> Result<Self> {
        let source = if path.is_dir() {
            let index = path.join(INDEX_FILE);
            if index.is_file() {
                index
            } else {
                path.join(SINGLE_FILE)
            }
        } else {
            path.to_path_buf()
        };
        let is_index = source
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.ends_with(".json"));
        let mut entries = BTreeMap::new();
        if is_index {
            let text = std::fs::read_to_string(&source).map_err(|e| Error::io(&source, e))?;
            let value: Value = serde_json::from_str(&text).map_err(|e| Error::Format {
                path: source.clone(),
                message: e.to_string(),
            })?;
            let map = value
                .get("weight_map")
                .and_then(Value::as_object)
                .ok_or_else(|| Error::Format {
                    path: source.clone(),
                    message: "no `weight_map` object".into(),
                })?;
            let dir = source.parent().unwrap_or(Path::new("."));
            // shard file → the names the index puts there (under the prefix)
            let mut shards: HashMap<String, Vec<String>> = HashMap::new();
            for (name, file) in map {
                if !name.starts_with(prefix) {
                    continue;
                }
                let file = file.as_str().ok_or_else(|| Error::Format {
                    path: source.clone(),
                    message: format!("`weight_map.{name}` is not a file name"),
                })?;
                shards
                    .entry(file.to_string())
                    .or_default()
                    .push(name.clone());
            }
            for (file, names) in shards {
                let shard = dir.join(&file);
                let mut header = read_header(&shard)?;
                for name in names {
                    let e = header.remove(&name).ok_or_else(|| {
                        st_err(
                            &shard,
                            format!(
                                "tensor `{name}` is listed in {INDEX_FILE} but not in this shard"
                            ),
                        )
                    })?;
                    entries.insert(name, e);
                }
            }
        } else {
            entries = read_header(&source)?;
            entries.retain(|k, _| k.starts_with(prefix));
        }
        Ok(Self { source, entries })
    }

    /// The file errors name.
    pub fn source(&self) -> &Path {
        &self.source
    }

    /// Names indexed (all under the prefix), sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.entries.keys().map(String::as_str)
    }

    /// The shape of `name`, if present.
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.entries.get(name).map(|e| e.shape.as_slice())
    }

    /// Where the bytes of `name` live: `(file, safetensors dtype, shape, start, end)`, the
    /// byte range absolute in `file` (for copying a tensor without decoding it).
    pub fn location(&self, name: &str) -> Option<(&Path, &str, &[usize], u64, u64)> {
        self.entries.get(name).map(|e| {
            (
                e.file.as_path(),
                e.dtype.as_str(),
                e.shape.as_slice(),
                e.start,
                e.end,
            )
        })
    }

    /// Whether `name` is present.
    pub fn contains(&self, name: &str) -> bool {
        self.entries.contains_key(name)
    }

    /// Read rows `first .. first + count` of the first dimension of `name` as `f32` values
    /// (row-major), without reading the rest of the tensor. Float (F32, BF16, F16), integer
    /// (I64, I32, U8) and BOOL tensors are accepted.
    pub fn read_rows(&self, name: &str, first: usize, count: usize) -> Result<Vec<f32>> {
        let e = self.entries.get(name).ok_or_else(|| Error::MissingTensor {
            path: self.source.clone(),
            name: name.to_string(),
        })?;
        let width: usize = match e.dtype.as_str() {
            "F32" | "I32" => 4,
            "BF16" | "F16" => 2,
            "I64" => 8,
            "U8" | "BOOL" => 1,
            other => {
                return Err(st_err(
                    &e.file,
                    format!("tensor `{name}` has dtype {other}; expected a float, integer or bool"),
                ))
            }
        };
        let rows = e.shape.first().copied().unwrap_or(1);
        let row: usize = e.shape.iter().skip(1).product();
        let total: usize = e.shape.iter().product();
        if e.end - e.start != (total * width) as u64 || first + count > rows {
            return Err(st_err(
                &e.file,
                format!(
                    "tensor `{name}` {:?} ({}): rows {first}..{} are not in it",
                    e.shape,
                    e.dtype,
                    first + count
                ),
            ));
        }
        let mut f = File::open(&e.file).map_err(|err| Error::io(&e.file, err))?;
        f.seek(SeekFrom::Start(e.start + (first * row * width) as u64))
            .map_err(|err| Error::io(&e.file, err))?;
        let mut bytes = vec![0u8; count * row * width];
        f.read_exact(&mut bytes)
            .map_err(|err| Error::io(&e.file, err))?;
        if e.dtype == "F16" {
            let n = bytes.len() / 2;
            let t = Tensor::from_raw_buffer(&bytes, DType::F16, &[n], &Device::Cpu)?;
            return Ok(t.to_dtype(DType::F32)?.to_vec1::<f32>()?);
        }
        let c = |b: &[u8]| -> f32 {
            match e.dtype.as_str() {
                "F32" => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                "I32" => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                // bf16 is the upper half of an f32.
                "BF16" => f32::from_bits(u32::from(u16::from_le_bytes([b[0], b[1]])) << 16),
                "I64" => {
                    i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
                }
                _ => b[0] as f32,
            }
        };
        Ok(bytes.chunks_exact(width).map(c).collect())
    }

    /// Read `name` as an `f32` tensor of exactly `shape` (F32, BF16 and F16 are accepted).
    /// A missing tensor is [`Error::MissingTensor`], another shape [`Error::TensorShape`].
    pub fn load(&self, name: &str, shape: &[usize], device: &Device) -> Result<Tensor> {
        let e = self.entries.get(name).ok_or_else(|| Error::MissingTensor {
            path: self.source.clone(),
            name: name.to_string(),
        })?;
        if e.shape != shape {
            return Err(Error::TensorShape {
                path: e.file.clone(),
                name: name.to_string(),
                expected: shape.to_vec(),
                got: e.shape.clone(),
            });
        }
        let (dtype, width) = match e.dtype.as_str() {
            "F32" => (DType::F32, 4),
            "BF16" => (DType::BF16, 2),
            "F16" => (DType::F16, 2),
            other => {
                return Err(st_err(
                    &e.file,
                    format!("tensor `{name}` has dtype {other}; expected F32, BF16 or F16"),
                ))
            }
        };
        let count: usize = shape.iter().product();
        if e.end - e.start != (count * width) as u64 {
            return Err(st_err(
                &e.file,
                format!(
                    "tensor `{name}`: {} bytes for {count} {} values",
                    e.end - e.start,
                    e.dtype
                ),
            ));
        }
        let mut f = File::open(&e.file).map_err(|err| Error::io(&e.file, err))?;
        f.seek(SeekFrom::Start(e.start))
            .map_err(|err| Error::io(&e.file, err))?;
        let mut bytes = vec![0u8; (e.end - e.start) as usize];
        f.read_exact(&mut bytes)
            .map_err(|err| Error::io(&e.file, err))?;
        let t = Tensor::from_raw_buffer(&bytes, dtype, shape, device)?;
        Ok(t.to_dtype(DType::F32)?)
    }
}
