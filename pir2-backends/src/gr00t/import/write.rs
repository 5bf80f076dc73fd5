//! Writing our layout: the import itself ([`import_checkpoint`]), which plans, exports the
//! head's ONNX graphs, copies the tensors (bytes as stored) and GR00T's files, writes the
//! embodiment file, brings in (and rewrites) the backbone graphs, all into a hidden sibling of
//! the output directory that is moved into place at the end.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use candle_core::Device;
use serde_json::{Map, Value};

use super::plan::{plan, ImportOptions};
use super::read::{
    err, from_head, processor_file, CONFIG_FILE, EMBODIMENT_ID_FILE, PROCESSOR_FILE,
    STATISTICS_FILE,
};
use crate::error::{Error, Result};
use crate::gr00t::config::EMBED_TOKENS_KEY;
use crate::gr00t::n17::{Gr00tN17Head, TensorIndex, SINGLE_FILE};
use crate::gr00t::onnx_f32::{convert_bf16_to_f32, has_bf16, Bf16Report};

/// A file the import could not produce, and how to add it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MissingFile {
    /// Path relative to the output directory.
    pub file: String,
    /// How to add it.
    pub how: String,
}

/// What [`import_checkpoint`] wrote.
#[derive(Debug, Clone)]
pub struct ImportSummary {
    /// The output directory.
    pub out: PathBuf,
    /// The files written, relative to `out`, sorted.
    pub files: Vec<String>,
    /// The embodiment imported.
    pub embodiment_tag: String,
    /// Its slot.
    pub embodiment_id: i64,
    /// The chunk length `H` (the action modality's `delta_indices`).
    pub horizon: usize,
    /// State and action widths.
    pub state_dim: usize,
    /// See [`Self::state_dim`].
    pub action_dim: usize,
    /// `[policy] trained` of the written embodiment (`flow`, `pi_r2`, …).
    pub trained: String,
    /// `[policy] mode` of the written embodiment.
    pub mode: String,
    /// `[policy] nfe` of the written embodiment.
    pub nfe: usize,
    /// Whether the head has πR²'s per-position AdaLN heads.
    pub position_heads: bool,
    /// Backbone graphs rewritten from bfloat16 to float32: `(file, report)`.
    pub converted: Vec<(String, Bf16Report)>,
    /// What the user must still add before `pir2 gr00t run`.
    pub missing: Vec<MissingFile>,
}

/// What the write step produced: converted graphs and the files still missing.
type Written = (Vec<(String, Bf16Report)>, Vec<MissingFile>);

/// Write the tensors `names` of the indices to one safetensors file, bytes copied from their
/// sources as stored (no conversion).
fn write_safetensors(out: &Path, tensors: &[(&TensorIndex, String)]) -> Result<()> {
    let io = |source| Error::Read {
        path: out.to_path_buf(),
        source,
    };
    let mut header = Map::new();
    let mut at = 0u64;
    let mut parts = Vec::new();
    for (index, name) in tensors {
        let (file, dtype, shape, start, end) = index
            .location(name)
            .ok_or_else(|| err(index.source(), name.clone(), "is missing"))?;
        header.insert(
            name.clone(),
            serde_json::json!({"dtype": dtype, "shape": shape, "data_offsets": [at, at + end - start]}),
        );
        at += end - start;
        parts.push((file.to_path_buf(), start, end));
    }
    let mut h = serde_json::to_vec(&Value::Object(header)).map_err(|e| Error::Parse {
        path: out.to_path_buf(),
        message: e.to_string(),
    })?;
    while h.len() % 8 != 0 {
        h.push(b' ');
    }
    let mut f = std::io::BufWriter::new(File::create(out).map_err(io)?);
    f.write_all(&(h.len() as u64).to_le_bytes()).map_err(io)?;
    f.write_all(&h).map_err(io)?;
    for (file, start, end) in parts {
        let mut src = File::open(&file).map_err(|source| Error::Read {
            path: file.clone(),
            source,
        })?;
        src.seek(SeekFrom::Start(start))
            .map_err(|source| Error::Read {
                path: file.clone(),
                source,
            })?;
        let copied = std::io::copy(&mut src.take(end - start), &mut f).map_err(io)?;
        if copied != end - start {
            return Err(err(
                &file,
                "(tensor data)",
                "is shorter than its header says",
            ));
        }
    }
    f.flush().map_err(io)?;
    Ok(())
}

fn copy(from: &Path, to: &Path) -> Result<()> {
    std::fs::copy(from, to).map_err(|source| Error::Read {
        path: from.to_path_buf(),
        source,
    })?;
    Ok(())
}

/// The NVIDIA exporter's file for `role` in `dir` (or `dir/onnx`), f32 preferred.
fn exported(dir: &Path, role: &str) -> Option<PathBuf> {
    for d in [dir.to_path_buf(), dir.join("onnx")] {
        for p in ["fp32", "bf16"] {
            let f = d.join(format!("{role}_{p}.onnx"));
            if f.is_file() {
                return Some(f);
            }
        }
    }
    None
}

/// Import the GR00T N1.7 checkpoint `ckpt` into `out` (see the module docs). `out` must not
/// exist or be empty; on an error nothing is left there.
pub fn import_checkpoint(ckpt: &Path, out: &Path, opts: &ImportOptions) -> Result<ImportSummary> {
    if out.exists() {
        let empty = out.is_dir()
            && std::fs::read_dir(out)
                .map_err(|source| Error::Read {
                    path: out.to_path_buf(),
                    source,
                })?
                .next()
                .is_none();
        if !empty {
            return Err(err(
                out,
                "--out",
                "exists and is not empty; choose a new directory (nothing was written)",
            ));
        }
    }
    if !(opts.control_hz.is_finite() && opts.control_hz > 0.0) {
        return Err(err(
            out,
            "--control-hz",
            format!("must be > 0, got {}", opts.control_hz),
        ));
    }
    let backbone = match &opts.backbone_onnx {
        None => None,
        Some(d) => {
            let (vit, llm) = (exported(d, "vit"), exported(d, "llm"));
            match (vit, llm) {
                (Some(v), Some(l)) => Some((v, l)),
                (v, l) => {
                    let missing: Vec<&str> =
                        [("vit_{fp32,bf16}.onnx", v), ("llm_{bf16,fp32}.onnx", l)]
                            .into_iter()
                            .filter(|(_, f)| f.is_none())
                            .map(|(n, _)| n)
                            .collect();
                    return Err(err(
                        d,
                        missing.join(" and "),
                        "is missing from the exporter's directory (export with \
                         `--export-mode full_pipeline`)",
                    ));
                }
            }
        }
    };
    let plan = plan(ckpt, opts)?;
    let device = Device::Cpu;
    // The checkpoint's head, with its own delay table (a πR² head) or a zero one (GR00T's
    // released head: exactly what it computes), and its per-position heads if it has them.
    let head = Gr00tN17Head::trainable_from_index(
        &plan.index,
        plan.cfg.clone(),
        plan.emb.d_vis_max,
        &device,
    )
    .map_err(|e| from_head(e, ckpt))?;
    let position_heads = head.position_heads().is_some();
    let export =
        crate::gr00t::n17::export::export_gr00t_n17(&head, plan.emb.horizon).map_err(|e| {
            Error::Gr00tCandle {
                path: ckpt.to_path_buf(),
                source: Box::new(e),
            }
        })?;
    drop(head);

    let name = out
        .file_name()
        .ok_or_else(|| err(out, "--out", "has no directory name"))?;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| Error::Read { path, source }
    };
    std::fs::create_dir_all(&parent).map_err(io(&parent))?;
    let tmp = parent.join(format!(
        ".{}.import-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(io(&tmp))?;
    }
    std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
    let written = (|| -> Result<Written> {
        export
            .write(&tmp, crate::gr00t::n17::export::WeightStorage::Auto)
            .map_err(|e| Error::Gr00tCandle {
                path: tmp.clone(),
                source: Box::new(e),
            })?;
        copy(&plan.config_path, &tmp.join(CONFIG_FILE))?;
        copy(&plan.processor_path, &tmp.join(PROCESSOR_FILE))?;
        copy(&plan.statistics_path, &tmp.join(STATISTICS_FILE))?;
        copy(&plan.embodiment_id_path, &tmp.join(EMBODIMENT_ID_FILE))?;
        let mut tensors: Vec<(&TensorIndex, String)> = plan
            .index
            .names()
            .map(|n| (&plan.index, n.to_string()))
            .collect();
        if let Some(e) = &plan.embed {
            tensors.push((e, EMBED_TOKENS_KEY.to_string()));
        }
        write_safetensors(&tmp.join(SINGLE_FILE), &tensors)?;
        let toml = plan.emb.to_toml()?;
        std::fs::write(tmp.join("embodiment.toml"), toml).map_err(io(&tmp))?;
        let mut missing = Vec::new();
        let mut tokenizer = false;
        for f in ["tokenizer.json", "tokenizer_config.json"] {
            let src = processor_file(ckpt, f);
            if src.is_file() {
                copy(&src, &tmp.join(f))?;
                tokenizer |= f == "tokenizer.json";
            }
        }
        if !tokenizer {
            missing.push(MissingFile {
                file: "tokenizer.json".into(),
                how: format!(
                    "the VLM's tokenizer: `tokenizer.json` of the Hugging Face model `{}` \
                     (processor_config.json `processor_kwargs.model_name`), copied into the \
                     directory",
                    plan.model_name
                ),
            });
        }
        let mut converted = Vec::new();
        let onnx = tmp.join("onnx");
        match &backbone {
            Some((vit, llm)) => {
                for (role, src) in [("vit", vit), ("llm", llm)] {
                    let bf16 = has_bf16(src)?;
                    let precision = if bf16 && opts.keep_bf16 {
                        "bf16"
                    } else {
                        "fp32"
                    };
                    let dst = onnx.join(format!("{role}_{precision}.onnx"));
                    let report = if bf16 && opts.keep_bf16 {
                        crate::gr00t::onnx_f32::copy_onnx(src, &dst)?
                    } else {
                        convert_bf16_to_f32(src, &dst)?
                    };
                    if report.changed() {
                        converted.push((format!("onnx/{role}_{precision}.onnx"), report));
                    }
                }
            }
            None => missing.push(MissingFile {
                file: "onnx/vit_fp32.onnx, onnx/llm_fp32.onnx".into(),
                how: format!(
                    "the backbone: the checkpoint holds PyTorch weights, not ONNX graphs. Export \
                     them with NVIDIA's exporter (Isaac-GR00T `scripts/deployment/export_onnx_n1d7.py \
                     --model-path {} --dataset-path DATASET --output-dir EXPORT --export-mode \
                     full_pipeline --embodiment-tag TAG`), then import again with \
                     `--backbone-onnx EXPORT` (its bfloat16 LLM is rewritten to float32 for \
                     ONNX Runtime's CPU provider; `--keep-bf16` keeps it for --ep cuda|tensorrt)",
                    ckpt.display()
                ),
            }),
        }
        Ok((converted, missing))
    })();
    let (converted, missing) = match written {
        Ok(x) => x,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    let mut files = Vec::new();
    list_files(&tmp, &tmp, &mut files).map_err(io(&tmp))?;
    files.sort();
    if out.exists() {
        std::fs::remove_dir(out).map_err(io(out))?;
    }
    std::fs::rename(&tmp, out).map_err(io(out))?;
    Ok(ImportSummary {
        out: out.to_path_buf(),
        files,
        embodiment_tag: plan.tag,
        embodiment_id: plan.emb.embodiment_id,
        horizon: plan.emb.horizon,
        state_dim: plan.emb.state_dim(),
        action_dim: plan.emb.action_dim(),
        trained: crate::gr00t::config::policy_name(plan.emb.policy.trained),
        mode: plan.emb.policy.mode.name().to_string(),
        nfe: plan.emb.policy.nfe,
        position_heads,
        converted,
        missing,
    })
}

fn list_files(root: &Path, dir: &Path, out: &mut Vec<String>) -> std::io::Result<()> {
    for e in std::fs::read_dir(dir)? {
        let p = e?.path();
        if p.is_dir() {
            list_files(root, &p, out)?;
        } else if let Ok(r) = p.strip_prefix(root) {
            out.push(r.to_string_lossy().into_owned());
        }
    }
    Ok(())
}
