//! safetensors files (weights, checkpoints) and atomic writes.

use std::collections::HashMap;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::error::{Error, Result};

/// Tensors (name → little-endian data) and string metadata, to be written as one
/// safetensors file.
#[derive(Debug, Default)]
pub(crate) struct TensorWriter {
    tensors: Vec<(String, Dtype, Vec<usize>, Vec<u8>)>,
    meta: HashMap<String, String>,
}

impl TensorWriter {
    pub fn f32(&mut self, name: &str, v: &[f32]) {
        let bytes = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        self.tensors
            .push((name.to_string(), Dtype::F32, vec![v.len()], bytes));
    }

    pub fn f64(&mut self, name: &str, v: &[f64]) {
        let bytes = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        self.tensors
            .push((name.to_string(), Dtype::F64, vec![v.len()], bytes));
    }

    pub fn meta(&mut self, key: &str, value: impl ToString) {
        self.meta.insert(key.to_string(), value.to_string());
    }

    /// Serialise and write atomically to `path` (temporary file, fsync, rename, fsync of
    /// the directory), so a crash leaves either the old or the new file.
    pub fn write(self, path: &Path) -> Result<()> {
        let views: Vec<(String, TensorView<'_>)> = self
            .tensors
            .iter()
            .map(|(n, d, s, b)| {
                TensorView::new(*d, s.clone(), b)
                    .map(|v| (n.clone(), v))
                    .map_err(|e| format_err(path, format!("tensor {n}: {e}")))
            })
            .collect::<Result<_>>()?;
        let bytes = safetensors::serialize(views, Some(self.meta))
            .map_err(|e| format_err(path, format!("cannot serialise: {e}")))?;
        write_atomic(path, &bytes)
    }
}

/// Write `bytes` to `path` through `path.tmp` + fsync + rename.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    let io = |action: &'static str, p: &Path| {
        let p = p.to_path_buf();
        move |source| Error::PpoIo {
            action,
            path: p,
            source,
        }
    };
    let mut f = File::create(&tmp).map_err(io("cannot create", &tmp))?;
    f.write_all(bytes).map_err(io("cannot write", &tmp))?;
    f.sync_all().map_err(io("cannot sync", &tmp))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io("cannot rename into", path))?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        if let Ok(d) = File::open(dir) {
            // Persist the rename; not all platforms allow syncing a directory.
            let _ = d.sync_all();
        }
    }
    Ok(())
}

pub(crate) fn format_err(path: &Path, message: String) -> Error {
    Error::PpoFormat {
        path: path.to_path_buf(),
        message,
    }
}

/// A loaded safetensors file.
#[derive(Debug)]
pub(crate) struct TensorReader {
    path: PathBuf,
    bytes: Vec<u8>,
    meta: HashMap<String, String>,
}

impl TensorReader {
    pub fn open(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| Error::PpoIo {
            action: "cannot read",
            path: path.to_path_buf(),
            source,
        })?;
        let (_, md) = SafeTensors::read_metadata(&bytes)
            .map_err(|e| format_err(path, format!("not a safetensors file: {e}")))?;
        let meta = md.metadata().clone().unwrap_or_default();
        // Validate the whole file once.
        SafeTensors::deserialize(&bytes)
            .map_err(|e| format_err(path, format!("not a safetensors file: {e}")))?;
        Ok(Self {
            path: path.to_path_buf(),
            bytes,
            meta,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn meta(&self, key: &str) -> Result<&str> {
        self.meta
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| format_err(&self.path, format!("metadata `{key}` is missing")))
    }

    /// An optional metadata entry.
    pub fn meta_opt(&self, key: &str) -> Option<&str> {
        self.meta.get(key).map(String::as_str)
    }

    pub fn meta_parse<T: std::str::FromStr>(&self, key: &str) -> Result<T> {
        let s = self.meta(key)?;
        s.parse()
            .map_err(|_| format_err(&self.path, format!("metadata `{key}` = {s:?} is malformed")))
    }

    fn raw(&self, name: &str, dtype: Dtype, len: usize) -> Result<&[u8]> {
        let st = SafeTensors::deserialize(&self.bytes)
            .map_err(|e| format_err(&self.path, e.to_string()))?;
        let t = st
            .tensor(name)
            .map_err(|_| format_err(&self.path, format!("tensor `{name}` is missing")))?;
        if t.dtype() != dtype || t.shape().iter().product::<usize>() != len {
            return Err(format_err(
                &self.path,
                format!(
                    "tensor `{name}` is {:?} {:?}, expected {dtype:?} with {len} values",
                    t.dtype(),
                    t.shape()
                ),
            ));
        }
        let off = t.data().as_ptr() as usize - self.bytes.as_ptr() as usize;
        Ok(&self.bytes[off..off + t.data().len()])
    }

    pub fn f32(&self, name: &str, len: usize) -> Result<Vec<f32>> {
        let b = self.raw(name, Dtype::F32, len)?;
        Ok(b.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    pub fn f64(&self, name: &str, len: usize) -> Result<Vec<f64>> {
        let b = self.raw(name, Dtype::F64, len)?;
        Ok(b.chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8-byte chunk")))
            .collect())
    }
}
