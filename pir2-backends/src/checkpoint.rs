//! Checkpoint directories: `config.json` + `stats.json` + `model.safetensors` (f32), and
//! `identity.json` ([`Identity`]: the policy the weights were trained as and the SHA-256 of
//! `model.safetensors`). A checkpoint written before `identity.json` existed still loads; its
//! policy is then unrecorded ([`Checkpoint::identity`] is `None`).
//!
//! This layer is backend-independent (the ONNX Runtime / libtorch backends can read the
//! stats from it). [`save`] refuses to write into an existing directory; [`Checkpoint::take`]
//! hands out tensors by name and fails with one error naming a missing or misshapen tensor.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use safetensors::{tensor::TensorView, Dtype, SafeTensors};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use pir2_runtime::Policy;

use crate::config::{Config, Stats};
use crate::error::{Error, Result};

/// File name of the configuration.
pub const CONFIG_FILE: &str = "config.json";
/// File name of the normalisation statistics.
pub const STATS_FILE: &str = "stats.json";
/// File name of the weights.
pub const WEIGHTS_FILE: &str = "model.safetensors";
/// File name of the identity ([`Identity`]).
pub const IDENTITY_FILE: &str = "identity.json";

/// What a checkpoint is, recorded next to its weights in `identity.json`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Identity {
    /// The policy (training schedule) the weights were trained as; `None` when the writer
    /// did not know it (e.g. [`save`] of tensors from elsewhere).
    pub policy: Option<Policy>,
    /// SHA-256 of the bytes of `model.safetensors`, lowercase hex ([`weights_sha256`]).
    pub weights_sha256: String,
}

/// SHA-256 of `bytes` (the contents of `model.safetensors`), lowercase hex.
pub fn weights_sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// One named f32 tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTensor {
    /// Shape.
    pub shape: Vec<usize>,
    /// Row-major data.
    pub data: Vec<f32>,
}

/// A loaded checkpoint.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    /// The directory it came from.
    pub dir: PathBuf,
    /// Model configuration.
    pub config: Config,
    /// Normalisation statistics.
    pub stats: Stats,
    /// Weights by name.
    pub tensors: BTreeMap<String, NamedTensor>,
    /// The recorded identity (`identity.json`); `None` for a checkpoint written without one
    /// (policy and hash unrecorded).
    pub identity: Option<Identity>,
    /// SHA-256 of `model.safetensors` as read (computed, recorded or not).
    pub weights_sha256: String,
}

fn write_json<T: serde::Serialize>(path: &Path, v: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| Error::Format {
        path: path.to_owned(),
        message: e.to_string(),
    })?;
    write_durable(path, text.as_bytes())
}

/// Write `bytes` to a new file `path` and fsync it.
pub(crate) fn write_durable(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    f.write_all(bytes).map_err(|e| Error::io(path, e))?;
    f.sync_all().map_err(|e| Error::io(path, e))
}

/// fsync a directory (its entries: the files created or renamed in it).
fn sync_dir(path: &Path) -> Result<()> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| Error::io(path, e))
}

/// A temporary sibling of `dir` no other writer uses: `.<name>.tmp-<pid>-<nanos>-<n>`, `n`
/// counting the saves of this process.
fn unique_temp(dir: &Path) -> PathBuf {
    use std::sync::atomic::{AtomicU64, Ordering};
    static SAVES: AtomicU64 = AtomicU64::new(0);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let leaf = dir
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_default();
    dir.with_file_name(format!(
        ".{leaf}.tmp-{}-{nanos}-{}",
        std::process::id(),
        SAVES.fetch_add(1, Ordering::Relaxed)
    ))
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::Format {
        path: path.to_owned(),
        message: e.to_string(),
    })
}

/// Write a checkpoint into a new directory `dir` (its parent is created if needed).
/// Fails with [`Error::CheckpointExists`] if `dir` exists. The files are written into a
/// uniquely named temporary sibling, fsynced, and renamed into place.
pub fn save<'a>(
    dir: &Path,
    config: &Config,
    stats: &Stats,
    tensors: impl IntoIterator<Item = (String, Vec<usize>, &'a [f32])>,
) -> Result<()> {
    create_dir_durably(dir, |tmp| write_files(tmp, config, stats, None, tensors))
}

/// Create the new directory `dir` holding the files `fill` writes (its parent is created if
/// needed; [`Error::CheckpointExists`] if `dir` exists). `fill` writes into a temporary
/// sibling of our own (never another writer's) with [`write_durable`]; the directory is then
/// fsynced, renamed into place and the parent fsynced. A crash leaves either no `dir` or a
/// whole one, a failed `fill` leaves nothing behind, and two saves never share a temp
/// directory.
pub(crate) fn create_dir_durably(dir: &Path, fill: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    if dir.exists() {
        return Err(Error::CheckpointExists(dir.to_owned()));
    }
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_owned(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| Error::io(&parent, e))?;
    let tmp = unique_temp(dir);
    std::fs::create_dir(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let written = fill(&tmp).and_then(|()| sync_dir(&tmp));
    let renamed = written.and_then(|()| {
        if dir.exists() {
            return Err(Error::CheckpointExists(dir.to_owned()));
        }
        std::fs::rename(&tmp, dir).map_err(|e| Error::io(dir, e))
    });
    if let Err(e) = renamed {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    sync_dir(&parent)
}

/// The files of a checkpoint (config, stats, weights, identity with `policy`) in the
/// existing directory `dir`.
pub(crate) fn write_files<'a>(
    dir: &Path,
    config: &Config,
    stats: &Stats,
    policy: Option<Policy>,
    tensors: impl IntoIterator<Item = (String, Vec<usize>, &'a [f32])>,
) -> Result<()> {
    write_json(&dir.join(CONFIG_FILE), config)?;
    write_json(&dir.join(STATS_FILE), stats)?;
    let wpath = dir.join(WEIGHTS_FILE);
    let bytes = serialize_tensors(&wpath, tensors)?;
    write_durable(&wpath, &bytes)?;
    write_json(
        &dir.join(IDENTITY_FILE),
        &Identity {
            policy,
            weights_sha256: weights_sha256(&bytes),
        },
    )
}

/// Write f32 tensors (name, shape, data) as one fsynced safetensors file.
pub(crate) fn write_tensors<'a>(
    path: &Path,
    tensors: impl IntoIterator<Item = (String, Vec<usize>, &'a [f32])>,
) -> Result<()> {
    let bytes = serialize_tensors(path, tensors)?;
    write_durable(path, &bytes)
}

/// f32 tensors (name, shape, data) as the bytes of a safetensors file (`path` names it in
/// errors).
fn serialize_tensors<'a>(
    path: &Path,
    tensors: impl IntoIterator<Item = (String, Vec<usize>, &'a [f32])>,
) -> Result<Vec<u8>> {
    let st_err = |e: safetensors::SafeTensorError| Error::Safetensors {
        path: path.to_owned(),
        message: e.to_string(),
    };
    let owned: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .into_iter()
        .map(|(n, s, d)| (n, s, d.iter().flat_map(|v| v.to_le_bytes()).collect()))
        .collect();
    let mut views = Vec::with_capacity(owned.len());
    for (n, s, b) in &owned {
        views.push((
            n.clone(),
            TensorView::new(Dtype::F32, s.clone(), b).map_err(st_err)?,
        ));
    }
    safetensors::serialize(views, None).map_err(st_err)
}

impl Checkpoint {
    /// Read a checkpoint directory (validates the config and the stats' widths).
    pub fn load(dir: &Path) -> Result<Self> {
        let config: Config = read_json(&dir.join(CONFIG_FILE))?;
        config.validate()?;
        let stats: Stats = read_json(&dir.join(STATS_FILE))?;
        stats.validate(&config.spec)?;
        let wpath = dir.join(WEIGHTS_FILE);
        let bytes = std::fs::read(&wpath).map_err(|e| Error::io(&wpath, e))?;
        let st = SafeTensors::deserialize(&bytes).map_err(|e| Error::Safetensors {
            path: wpath.clone(),
            message: e.to_string(),
        })?;
        let mut tensors = BTreeMap::new();
        for (name, view) in st.tensors() {
            if view.dtype() != Dtype::F32 {
                return Err(Error::Safetensors {
                    path: wpath.clone(),
                    message: format!("tensor `{name}` is {:?}, expected F32", view.dtype()),
                });
            }
            let data = view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            tensors.insert(
                name,
                NamedTensor {
                    shape: view.shape().to_vec(),
                    data,
                },
            );
        }
        // After the weights parsed: a malformed file is named as such, not as a changed one.
        let sha = weights_sha256(&bytes);
        let ipath = dir.join(IDENTITY_FILE);
        let identity: Option<Identity> = if ipath.exists() {
            let id: Identity = read_json(&ipath)?;
            if id.weights_sha256 != sha {
                return Err(Error::Format {
                    path: ipath,
                    message: format!(
                        "records the weights' SHA-256 {} but {WEIGHTS_FILE} hashes to {sha}: \
                         the weights were replaced after the checkpoint was written",
                        id.weights_sha256
                    ),
                });
            }
            Some(id)
        } else {
            None
        };
        Ok(Self {
            dir: dir.to_owned(),
            config,
            stats,
            tensors,
            identity,
            weights_sha256: sha,
        })
    }

    /// Remove and return the tensor `name`, checking its shape.
    pub fn take(&mut self, name: &str, expected: &[usize]) -> Result<NamedTensor> {
        let path = self.dir.join(WEIGHTS_FILE);
        let t = self
            .tensors
            .remove(name)
            .ok_or_else(|| Error::MissingTensor {
                path: path.clone(),
                name: name.to_owned(),
            })?;
        if t.shape != expected {
            return Err(Error::TensorShape {
                path,
                name: name.to_owned(),
                expected: expected.to_vec(),
                got: t.shape,
            });
        }
        Ok(t)
    }

    /// Fail if any tensor was not taken (the weights belong to another architecture).
    pub fn expect_consumed(&self) -> Result<()> {
        match self.tensors.keys().next() {
            Some(name) => Err(Error::UnexpectedTensor {
                path: self.dir.join(WEIGHTS_FILE),
                name: name.clone(),
            }),
            None => Ok(()),
        }
    }
}
