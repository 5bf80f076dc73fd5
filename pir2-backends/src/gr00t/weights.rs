//! The pir2 side weights (`pir2_gr00t.safetensors`): the tensors GR00T applies outside its
//! ONNX graphs, plus the πR² delay table.
//!
//! | tensor                      | shape               | dtype     |                          |
//! |-----------------------------|---------------------|-----------|--------------------------|
//! | `delay_embedding.weight`    | `[d_vis_max+1, D_in]` | F32/BF16 | required (πR²)          |
//! | `position_embedding.weight` | `[≥H, D_in]`        | F32/BF16  | optional (`add_pos_embed`) |
//! | `vlln.weight`, `vlln.bias`  | `[D_vl]`            | F32/BF16  | optional (backbone LayerNorm) |

use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};

use crate::error::{Error, Result};

/// Name of the delay table.
pub const DELAY_EMBEDDING: &str = "delay_embedding.weight";
/// Name of GR00T's action position embedding.
pub const POSITION_EMBEDDING: &str = "position_embedding.weight";
/// Names of GR00T's `vlln` LayerNorm.
pub const VLLN_WEIGHT: &str = "vlln.weight";
/// See [`VLLN_WEIGHT`].
pub const VLLN_BIAS: &str = "vlln.bias";

/// The side-weights file, read once.
#[derive(Debug)]
pub struct SideWeights {
    path: PathBuf,
    bytes: Vec<u8>,
}

impl SideWeights {
    /// Read the file.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        SafeTensors::deserialize(&bytes).map_err(|e| Error::Parse {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        Ok(SideWeights {
            path: path.to_path_buf(),
            bytes,
        })
    }

    fn err(&self, tensor: &str, problem: String) -> Error {
        Error::Weights {
            path: self.path.clone(),
            tensor: tensor.to_string(),
            problem,
        }
    }

    /// A tensor as `f32` with its shape, or `None` if absent.
    pub fn get(&self, name: &str) -> Result<Option<(Vec<usize>, Vec<f32>)>> {
        let st = SafeTensors::deserialize(&self.bytes).map_err(|e| Error::Parse {
            path: self.path.clone(),
            message: e.to_string(),
        })?;
        let view = match st.tensor(name) {
            Ok(v) => v,
            Err(safetensors::SafeTensorError::TensorNotFound(_)) => return Ok(None),
            Err(e) => return Err(self.err(name, e.to_string())),
        };
        let data = view.data();
        let vals: Vec<f32> = match view.dtype() {
            Dtype::F32 => data
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            Dtype::BF16 => data
                .chunks_exact(2)
                .map(|c| f32::from_bits((u16::from_le_bytes([c[0], c[1]]) as u32) << 16))
                .collect(),
            other => {
                return Err(self.err(name, format!("has dtype {other:?}, expected F32 or BF16")))
            }
        };
        Ok(Some((view.shape().to_vec(), vals)))
    }

    /// The delay table `[d_vis_max + 1, d_in]` (required).
    pub fn delay_embedding(&self, d_vis_max: usize, d_in: usize) -> Result<Vec<f32>> {
        let (shape, v) = self
            .get(DELAY_EMBEDDING)?
            .ok_or_else(|| self.err(DELAY_EMBEDDING, "is missing".to_string()))?;
        if shape != [d_vis_max + 1, d_in] {
            return Err(self.err(
                DELAY_EMBEDDING,
                format!(
                    "has shape {shape:?}, expected [d_vis_max + 1, D_in] = [{}, {d_in}]",
                    d_vis_max + 1
                ),
            ));
        }
        Ok(v)
    }

    /// The first `h` rows of the position embedding `[≥h, d_in]`, if present.
    pub fn position_embedding(&self, h: usize, d_in: usize) -> Result<Option<Vec<f32>>> {
        let Some((shape, v)) = self.get(POSITION_EMBEDDING)? else {
            return Ok(None);
        };
        if shape.len() != 2 || shape[0] < h || shape[1] != d_in {
            return Err(self.err(
                POSITION_EMBEDDING,
                format!("has shape {shape:?}, expected [>= {h}, {d_in}]"),
            ));
        }
        Ok(Some(v[..h * d_in].to_vec()))
    }

    /// `vlln` LayerNorm `(weight, bias)` of width `d_vl`, if present.
    pub fn vlln(&self, d_vl: usize) -> Result<Option<(Vec<f32>, Vec<f32>)>> {
        let w = self.get(VLLN_WEIGHT)?;
        let b = self.get(VLLN_BIAS)?;
        match (w, b) {
            (None, None) => Ok(None),
            (Some((ws, w)), Some((bs, b))) => {
                if ws != [d_vl] || bs != [d_vl] {
                    return Err(self.err(
                        VLLN_WEIGHT,
                        format!("weight {ws:?} / bias {bs:?}, expected [{d_vl}]"),
                    ));
                }
                Ok(Some((w, b)))
            }
            (Some(_), None) => {
                Err(self.err(VLLN_BIAS, "is missing (vlln.weight is present)".into()))
            }
            (None, Some(_)) => {
                Err(self.err(VLLN_WEIGHT, "is missing (vlln.bias is present)".into()))
            }
        }
    }
}

/// Write `f32` tensors to a safetensors file (test set-up, tools).
pub fn write_f32(path: &Path, tensors: &[(&str, Vec<usize>, Vec<f32>)]) -> Result<()> {
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|(_, _, v)| v.iter().flat_map(|x| x.to_le_bytes()).collect())
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = tensors
        .iter()
        .zip(&bytes)
        .map(|((n, s, _), b)| {
            safetensors::tensor::TensorView::new(Dtype::F32, s.clone(), b)
                .map(|v| (n.to_string(), v))
                .map_err(|e| Error::Parse {
                    path: path.to_path_buf(),
                    message: format!("tensor `{n}`: {e}"),
                })
        })
        .collect::<Result<_>>()?;
    safetensors::serialize_to_file(views, None, path).map_err(|e| Error::Parse {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// The rows `ids` of the `[vocab, D]` table `key` in a GR00T checkpoint's safetensors, as
/// `f32` `[ids.len(), D]` (plus `D`). `index` (`model.safetensors.index.json`, used when it
/// exists) names the shard holding `key`; else the table is read from `single`
/// (`model.safetensors`). Only the header and the requested rows are read, so a
/// 150k-token table costs `ids.len()` rows of memory. F32 and BF16 tables are accepted; an
/// id outside the table is an error naming the id.
pub fn read_table_rows(
    index: &Path,
    single: &Path,
    key: &str,
    ids: &[i64],
) -> Result<(usize, Vec<f32>)> {
    let file = if index.exists() {
        let text = std::fs::read_to_string(index).map_err(|source| Error::Read {
            path: index.to_path_buf(),
            source,
        })?;
        let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| Error::Parse {
            path: index.to_path_buf(),
            message: e.to_string(),
        })?;
        let shard = v
            .get("weight_map")
            .and_then(|m| m.get(key))
            .and_then(|s| s.as_str())
            .ok_or_else(|| Error::Weights {
                path: index.to_path_buf(),
                tensor: key.to_string(),
                problem: "is not in the index's weight_map (set `vision.embed_tokens_key` of \
                          the embodiment config to the table's name)"
                    .into(),
            })?;
        if shard.contains("..") || Path::new(shard).is_absolute() {
            return Err(Error::Parse {
                path: index.to_path_buf(),
                message: format!("shard `{shard}` of `{key}` is not a file next to the index"),
            });
        }
        index.with_file_name(shard)
    } else {
        single.to_path_buf()
    };
    read_rows_from(&file, key, ids)
}

fn read_rows_from(path: &Path, key: &str, ids: &[i64]) -> Result<(usize, Vec<f32>)> {
    use std::io::{Read, Seek, SeekFrom};
    let io = |source| Error::Read {
        path: path.to_path_buf(),
        source,
    };
    let parse = |message: String| Error::Parse {
        path: path.to_path_buf(),
        message,
    };
    let bad = |problem: String| Error::Weights {
        path: path.to_path_buf(),
        tensor: key.to_string(),
        problem,
    };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let file_len = f.metadata().map_err(io)?.len();
    let mut n = [0u8; 8];
    f.read_exact(&mut n).map_err(io)?;
    let header_len = u64::from_le_bytes(n);
    if header_len > 100_000_000 || 8 + header_len > file_len {
        return Err(parse(format!(
            "safetensors header of {header_len} bytes does not fit the file"
        )));
    }
    let mut header = vec![0u8; header_len as usize];
    f.read_exact(&mut header).map_err(io)?;
    let header: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| parse(format!("header: {e}")))?;
    let entry = header.get(key).ok_or_else(|| {
        bad("is missing (set `vision.embed_tokens_key` of the embodiment config to the table's name)".into())
    })?;
    let dtype = entry.get("dtype").and_then(|d| d.as_str()).unwrap_or("");
    let shape: Vec<u64> = entry
        .get("shape")
        .and_then(|s| s.as_array())
        .map(|a| a.iter().filter_map(|x| x.as_u64()).collect())
        .unwrap_or_default();
    let offsets: Vec<u64> = entry
        .get("data_offsets")
        .and_then(|s| s.as_array())
        .map(|a| a.iter().filter_map(|x| x.as_u64()).collect())
        .unwrap_or_default();
    let width = match dtype {
        "F32" => 4u64,
        "BF16" => 2,
        other => return Err(bad(format!("has dtype {other:?}, expected F32 or BF16"))),
    };
    let [rows, d] = shape[..] else {
        return Err(bad(format!("has shape {shape:?}, expected [vocab, D]")));
    };
    let [start, end] = offsets[..] else {
        return Err(parse(format!("tensor `{key}` has no data_offsets")));
    };
    let data_start = 8 + header_len + start;
    if end < start || end - start != rows * d * width || data_start + (end - start) > file_len {
        return Err(bad(format!(
            "data [{start}, {end}) does not hold {rows}×{d} {dtype} values in the file"
        )));
    }
    let d = d as usize;
    let mut out = Vec::with_capacity(ids.len() * d);
    let mut row = vec![0u8; d * width as usize];
    for &id in ids {
        if id < 0 || id as u64 >= rows {
            return Err(bad(format!(
                "has {rows} rows; token id {id} is outside it (tokenizer and checkpoint differ?)"
            )));
        }
        f.seek(SeekFrom::Start(data_start + id as u64 * d as u64 * width))
            .map_err(io)?;
        f.read_exact(&mut row).map_err(io)?;
        if width == 4 {
            out.extend(
                row.chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
            );
        } else {
            out.extend(
                row.chunks_exact(2)
                    .map(|c| f32::from_bits((u16::from_le_bytes([c[0], c[1]]) as u32) << 16)),
            );
        }
    }
    Ok((d, out))
}
