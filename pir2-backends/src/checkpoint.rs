//! Checkpoint directories: `config.json` + `stats.json` + `model.safetensors` (f32).
//!
//! This layer is backend-independent (the ONNX Runtime / libtorch backends can read the
//! stats from it). [`save`] refuses to write into an existing directory; [`Checkpoint::take`]
//! hands out tensors by name and fails with one error naming a missing or misshapen tensor.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use safetensors::{tensor::TensorView, Dtype, SafeTensors};

use crate::config::{Config, Stats};
use crate::error::{Error, Result};

/// File name of the configuration.
pub const CONFIG_FILE: &str = "config.json";
/// File name of the normalisation statistics.
pub const STATS_FILE: &str = "stats.json";
/// File name of the weights.
pub const WEIGHTS_FILE: &str = "model.safetensors";

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
}

fn write_json<T: serde::Serialize>(path: &Path, v: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| Error::Format {
        path: path.to_owned(),
        message: e.to_string(),
    })?;
    std::fs::write(path, text).map_err(|e| Error::io(path, e))
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::Format {
        path: path.to_owned(),
        message: e.to_string(),
    })
}

/// Write a checkpoint into a new directory `dir` (its parent is created if needed).
/// Fails with [`Error::CheckpointExists`] if `dir` exists.
pub fn save<'a>(
    dir: &Path,
    config: &Config,
    stats: &Stats,
    tensors: impl IntoIterator<Item = (String, Vec<usize>, &'a [f32])>,
) -> Result<()> {
    if dir.exists() {
        return Err(Error::CheckpointExists(dir.to_owned()));
    }
    // Write into a sibling temp dir, then rename: a crash never leaves a half checkpoint.
    let tmp = dir.with_extension("partial");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| Error::io(&tmp, e))?;
    }
    std::fs::create_dir_all(&tmp).map_err(|e| Error::io(&tmp, e))?;
    write_json(&tmp.join(CONFIG_FILE), config)?;
    write_json(&tmp.join(STATS_FILE), stats)?;
    let wpath = tmp.join(WEIGHTS_FILE);
    let st_err = |e: safetensors::SafeTensorError| Error::Safetensors {
        path: wpath.clone(),
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
    let bytes = safetensors::serialize(views, None).map_err(st_err)?;
    std::fs::write(&wpath, bytes).map_err(|e| Error::io(&wpath, e))?;
    std::fs::rename(&tmp, dir).map_err(|e| Error::io(dir, e))
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
        Ok(Self {
            dir: dir.to_owned(),
            config,
            stats,
            tensors,
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
