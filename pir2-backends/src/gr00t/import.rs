//! `pir2 gr00t import`: a GR00T N1.7 checkpoint directory, as Isaac-GR00T writes and NVIDIA
//! releases it, to the checkpoint layout `pir2 run` and `pir2 gr00t train` read
//! (`docs/gr00t-contract.md`; the mapping is documented field by field in
//! `docs/gr00t-import.md`).
//!
//! **Input** (Isaac-GR00T; facts read at the commits named, file and lines):
//!
//! - `config.json`: the model configuration `Gr00tN1d7Config` (`model_type = "Gr00tN1d7"`),
//!   `gr00t/configs/model/gr00t_n1d7.py` @ 543b45271898211a63f5bf5e03633316bd6189f5,
//!   class `Gr00tN1d7Config`;
//! - the weights: `model.safetensors`, or `model.safetensors.index.json` + the shards
//!   `model-0000K-of-0000N.safetensors` (Hugging Face's `save_pretrained`); the action head is
//!   every tensor under `action_head.`, the VLM's token table is
//!   `backbone.model.model.language_model.embed_tokens.weight`. The released file set is the one
//!   `scripts/deployment/README.md` @ 1ca4b07087c8497c75aecf072dd95519f23726c2 downloads
//!   ("Step 0", its `hf download --include` list): `config.json`, `embodiment_id.json`, `model-*.safetensors`,
//!   `model.safetensors.index.json`, `processor_config.json`, `statistics.json`;
//! - `processor_config.json`, `statistics.json`, `embodiment_id.json`: written together by
//!   `Gr00tN1d7Processor.save_pretrained`,
//!   `gr00t/model/gr00t_n1d7/processing_gr00t_n1d7.py` @ 1852a8c13382b25cb656331b660600859925cfa0
//!   (`save_pretrained`: `{"processor_class", "processor_kwargs": {modality_configs, image and VLM
//!   settings, max dims, normalisation flags}}`, the statistics as
//!   `{tag: {"state"|"action"|"relative_action": {group: {stat: [..]}}}}`, and `{tag: slot}`);
//!   the modality configs are `ModalityConfig` dataclasses serialised by `to_json_serializable`
//!   (enums by name: `"RELATIVE"`, `"NON_EEF"`, `"XYZ_ROT6D"`), `gr00t/data/types.py` @
//!   be889e7a1ac76a409eaca575a5139338e41dedfc (`ModalityConfig`, `ActionConfig` and its enums) and
//!   `gr00t/data/utils.py` @ 066d167414aed0c97541274fdb1b06ff36564868
//!   (`to_json_serializable`, `parse_modality_configs`);
//! - how a group is normalised: `StateActionProcessor`,
//!   `gr00t/data/state_action/state_action_processor.py` @
//!   98a45fe6604c96ff2244750473aeee6efb43b08b (`_compute_normalization_parameters`: `use_percentiles` picks
//!   `q01`/`q99`, relative groups take `relative_action` statistics; `apply_state`: state groups are
//!   sin/cos when `apply_sincos_state_encoding` and listed in `sin_cos_embedding_keys`, mean/std
//!   when listed in `mean_std_embedding_keys`, else min/max clipped when `clip_outliers`);
//! - the image pipeline: `build_image_transformations_albumentations`,
//!   `gr00t/model/gr00t_n1d7/image_augmentations.py` @ 1852a8c13382b25cb656331b660600859925cfa0
//!   (`build_image_transformations_albumentations`: `crop_fraction` else `image_crop_size[0] / image_target_size[0]`;
//!   `SmallestMaxSize(shortest_image_edge)` else a plain `Resize(image_target_size)`).
//!
//! **Output**: `config.json` (copied), `model.safetensors` (the `action_head.*` tensors and the
//! token table, bytes copied as stored), the four ONNX action-head graphs and
//! `pir2_gr00t.safetensors` (`n17::export`, with a zero delay table: exactly GR00T's head),
//! `embodiment.toml` (mapped, `[policy] trained = "flow"`: a released head is a flow-matching
//! head, not πR²-fine-tuned), `statistics.json`, `embodiment_id.json` and
//! `processor_config.json` (copied), the VLM tokenizer when the checkpoint has one, and, with
//! [`ImportOptions::backbone_onnx`], GR00T's exported ViT and LLM graphs (bfloat16 ones
//! rewritten to float32 by [`super::onnx_f32`] unless [`ImportOptions::keep_bf16`]).
//!
//! Every field of the GR00T files either maps, is known to be training-only (ignored, listed
//! in the docs), or is refused: one [`Gr00tError::Import`] naming the file and the field
//! (JSON path), before anything is written. The files are written to a hidden sibling of the
//! output directory and moved into place at the end.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use candle_core::Device;
use serde_json::{Map, Value};

use super::config::{
    EmbodimentConfig, Group, GroupFormat, ImagePipeline, Norm, Normalizer, EMBED_TOKENS_KEY,
};
use super::error::{Gr00tError, Result};
use super::n17::{Gr00tN17Config, Gr00tN17Head, TensorIndex, INDEX_FILE, PREFIX, SINGLE_FILE};
use super::onnx_f32::{convert_bf16_to_f32, has_bf16, Bf16Report};

/// GR00T's model configuration file.
pub const CONFIG_FILE: &str = "config.json";
/// GR00T's processor configuration (`Gr00tN1d7Processor.save_pretrained`).
pub const PROCESSOR_FILE: &str = "processor_config.json";
/// GR00T's normalisation statistics.
pub const STATISTICS_FILE: &str = "statistics.json";
/// GR00T's embodiment slots `{tag: id}`.
pub const EMBODIMENT_ID_FILE: &str = "embodiment_id.json";

/// The VLM the prompt and vision defaults of pir2 are those of (GR00T N1.7's default
/// `model_name`).
pub const N17_VLM: &str = "nvidia/Cosmos-Reason2-2B";

/// Options of [`import_checkpoint`].
#[derive(Debug, Clone)]
pub struct ImportOptions {
    /// The embodiment tag (a key of `processor_kwargs.modality_configs`); `None`: the
    /// checkpoint's only one (several are an error listing them).
    pub embodiment_tag: Option<String>,
    /// A directory holding NVIDIA's ONNX export of this checkpoint
    /// (`export_onnx_n1d7.py --export-mode full_pipeline --output-dir DIR`): its
    /// `vit_{fp32,bf16}.onnx` and `llm_{bf16,fp32}.onnx` are imported.
    pub backbone_onnx: Option<PathBuf>,
    /// Copy bfloat16 backbone graphs as they are (for `--ep cuda|tensorrt`) instead of
    /// rewriting them to float32 (which ONNX Runtime's CPU provider needs).
    pub keep_bf16: bool,
    /// Control rate, Hz (not in GR00T's files; the dataset's fps).
    pub control_hz: f64,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            embodiment_tag: None,
            backbone_onnx: None,
            keep_bf16: false,
            control_hz: 25.0,
        }
    }
}

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
    /// Backbone graphs rewritten from bfloat16 to float32: `(file, report)`.
    pub converted: Vec<(String, Bf16Report)>,
    /// What the user must still add before `pir2 run`.
    pub missing: Vec<MissingFile>,
}

fn err(path: &Path, field: impl Into<String>, problem: impl Into<String>) -> Gr00tError {
    Gr00tError::Import {
        path: path.to_path_buf(),
        field: field.into(),
        problem: problem.into(),
    }
}

/// A JSON value with the file it is in and its JSON path, so every error names both.
#[derive(Clone, Copy)]
struct Node<'a> {
    v: &'a Value,
    path: &'a Path,
}

struct At<'a> {
    node: Node<'a>,
    field: String,
}

impl<'a> At<'a> {
    fn root(v: &'a Value, path: &'a Path, field: &str) -> Self {
        At {
            node: Node { v, path },
            field: field.to_string(),
        }
    }
    fn err(&self, problem: impl Into<String>) -> Gr00tError {
        err(self.node.path, &self.field, problem)
    }
    fn sub(&self, key: &str) -> String {
        if self.field.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.field)
        }
    }
    fn obj(&self) -> Result<&'a Map<String, Value>> {
        self.node
            .v
            .as_object()
            .ok_or_else(|| self.err(format!("must be an object, got {}", short(self.node.v))))
    }
    /// The value at `key` (absent or null: `None`).
    fn opt(&self, key: &str) -> Result<Option<At<'a>>> {
        Ok(match self.obj()?.get(key) {
            None | Some(Value::Null) => None,
            Some(v) => Some(At {
                node: Node {
                    v,
                    path: self.node.path,
                },
                field: self.sub(key),
            }),
        })
    }
    fn key(&self, key: &str) -> Result<At<'a>> {
        self.opt(key)?
            .ok_or_else(|| err(self.node.path, self.sub(key), "is missing"))
    }
    fn bool(&self) -> Result<bool> {
        self.node
            .v
            .as_bool()
            .ok_or_else(|| self.err(format!("must be true or false, got {}", short(self.node.v))))
    }
    fn u64(&self) -> Result<u64> {
        self.node.v.as_u64().ok_or_else(|| {
            self.err(format!(
                "must be a non-negative integer, got {}",
                short(self.node.v)
            ))
        })
    }
    fn f64(&self) -> Result<f64> {
        self.node
            .v
            .as_f64()
            .ok_or_else(|| self.err(format!("must be a number, got {}", short(self.node.v))))
    }
    fn str(&self) -> Result<&'a str> {
        self.node
            .v
            .as_str()
            .ok_or_else(|| self.err(format!("must be a string, got {}", short(self.node.v))))
    }
    fn items(&self) -> Result<Vec<At<'a>>> {
        let a = self
            .node
            .v
            .as_array()
            .ok_or_else(|| self.err(format!("must be a list, got {}", short(self.node.v))))?;
        Ok(a.iter()
            .enumerate()
            .map(|(i, v)| At {
                node: Node {
                    v,
                    path: self.node.path,
                },
                field: format!("{}[{i}]", self.field),
            })
            .collect())
    }
    fn strings(&self) -> Result<Vec<String>> {
        self.items()?
            .iter()
            .map(|a| a.str().map(str::to_string))
            .collect()
    }
    fn ints(&self) -> Result<Vec<i64>> {
        self.items()?
            .iter()
            .map(|a| {
                a.node
                    .v
                    .as_i64()
                    .ok_or_else(|| a.err(format!("must be an integer, got {}", short(a.node.v))))
            })
            .collect()
    }
    /// Refuse keys outside `known`.
    fn only(&self, known: &[&str], whose: &str) -> Result<()> {
        for k in self.obj()?.keys() {
            if !known.contains(&k.as_str()) {
                return Err(err(
                    self.node.path,
                    self.sub(k),
                    format!(
                        "is not a field of {whose} that pir2 knows (known: {}); pir2 does not \
                         guess what it means",
                        known.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }
}

fn short(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 60 {
        format!(
            "{}…",
            &s[..s.char_indices().nth(57).map_or(s.len(), |(i, _)| i)]
        )
    } else {
        s
    }
}

fn read_json(path: &Path) -> Result<Value> {
    if !path.is_file() {
        return Err(err(
            path,
            path.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            "is missing (Isaac-GR00T writes it next to config.json)",
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|source| Gr00tError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|e| Gr00tError::Parse {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// The processor's files are in the checkpoint root; a checkpoint whose processor was saved
/// into `processor/` is read from there.
fn processor_file(ckpt: &Path, name: &str) -> PathBuf {
    let root = ckpt.join(name);
    let sub = ckpt.join("processor").join(name);
    if !root.exists() && sub.exists() {
        sub
    } else {
        root
    }
}

/// A crate error of the head loader as one import error naming the file and the tensor or
/// field.
fn from_head(e: crate::error::Error, fallback: &Path) -> Gr00tError {
    use crate::error::Error as E;
    match e {
        E::MissingTensor { path, name } => err(&path, name, "is missing"),
        E::TensorShape {
            path,
            name,
            expected,
            got,
        } => err(
            &path,
            name,
            format!("has shape {got:?}; config.json's sizes need {expected:?}"),
        ),
        E::UnexpectedTensor { path, name } => err(
            &path,
            name,
            "is not a tensor of the action head config.json describes",
        ),
        E::Format { path, message } => {
            let field = message
                .split('`')
                .nth(1)
                .unwrap_or("(file)")
                .trim_start_matches('`')
                .to_string();
            err(&path, field, message)
        }
        E::Safetensors { path, message } => err(&path, "(safetensors header)", message),
        E::Io { path, source } => Gr00tError::Read { path, source },
        other => Gr00tError::Candle {
            path: fallback.to_path_buf(),
            source: Box::new(other),
        },
    }
}

/// `(rep, type, format, state_key)` of an `ActionConfig`, enum names as GR00T writes them.
type ActionCfg = (String, String, String, Option<String>);

/// What the write step produced: converted graphs and the files still missing.
type Written = (Vec<(String, Bf16Report)>, Vec<MissingFile>);

/// One modality of one embodiment (`ModalityConfig`).
struct Modality {
    delta_indices: Vec<i64>,
    keys: Vec<String>,
    sin_cos: Vec<String>,
    mean_std: Vec<String>,
    /// `(rep, type, format, state_key)` per key, enum names as GR00T writes them.
    actions: Option<Vec<ActionCfg>>,
}

fn modality(at: &At<'_>) -> Result<Modality> {
    at.only(
        &[
            "delta_indices",
            "modality_keys",
            "sin_cos_embedding_keys",
            "mean_std_embedding_keys",
            "action_configs",
            "exclude_state",
        ],
        "GR00T's ModalityConfig",
    )?;
    if let Some(x) = at.opt("exclude_state")? {
        if x.bool()? {
            return Err(x.err(
                "is true (the state is zeroed); pir2 always feeds the robot state to the head",
            ));
        }
    }
    let keys = at.key("modality_keys")?.strings()?;
    if keys.is_empty() {
        return Err(at.key("modality_keys")?.err("is empty"));
    }
    let list = |k: &str| -> Result<Vec<String>> {
        match at.opt(k)? {
            None => Ok(Vec::new()),
            Some(a) => a.strings(),
        }
    };
    let actions = match at.opt("action_configs")? {
        None => None,
        Some(a) => {
            let items = a.items()?;
            if items.len() != keys.len() {
                return Err(a.err(format!(
                    "has {} entries for {} modality_keys",
                    items.len(),
                    keys.len()
                )));
            }
            let mut v = Vec::new();
            for it in items {
                it.only(
                    &["rep", "type", "format", "state_key"],
                    "GR00T's ActionConfig",
                )?;
                let state_key = match it.opt("state_key")? {
                    None => None,
                    Some(s) => Some(s.str()?.to_string()),
                };
                v.push((
                    it.key("rep")?.str()?.to_string(),
                    it.key("type")?.str()?.to_string(),
                    it.key("format")?.str()?.to_string(),
                    state_key,
                ));
            }
            Some(v)
        }
    };
    Ok(Modality {
        delta_indices: at.key("delta_indices")?.ints()?,
        keys,
        sin_cos: list("sin_cos_embedding_keys")?,
        mean_std: list("mean_std_embedding_keys")?,
        actions,
    })
}

/// The fields `Gr00tN1d7Processor.save_pretrained` writes into `processor_kwargs`.
const PROCESSOR_KWARGS: &[&str] = &[
    "modality_configs",
    "image_crop_size",
    "image_target_size",
    "use_albumentations",
    "random_rotation_angle",
    "color_jitter_params",
    "shortest_image_edge",
    "crop_fraction",
    "letter_box_transform",
    "model_name",
    "model_type",
    "formalize_language",
    "max_state_dim",
    "max_action_dim",
    "max_action_horizon",
    "use_percentiles",
    "use_mean_std",
    "clip_outliers",
    "apply_sincos_state_encoding",
    "use_relative_action",
    "exclude_state",
    "state_dropout_prob",
    "use_tactile",
    "tactile_state_keys",
    "tactile_input_shape",
    "tactile_embed_dim",
    "extra_augmentation_config",
];

/// The width of `tag.modality.group` in the statistics (its `min`, or `q01` with
/// percentiles).
fn stat_width(stats: &At<'_>, modality: &str, group: &str, stat: &str) -> Result<usize> {
    let g = stats.key(modality)?.key(group)?;
    let v = g.key(stat)?;
    let items = v.items()?;
    if items.is_empty() {
        return Err(v.err("is empty"));
    }
    // A per-slot table `[H, D]` (relative actions) has rows; a vector has numbers.
    match items[0].node.v {
        Value::Array(row) => Ok(row.len()),
        _ => Ok(items.len()),
    }
}

/// Everything read and checked before anything is written.
struct Plan {
    cfg: Gr00tN17Config,
    emb: EmbodimentConfig,
    tag: String,
    index: TensorIndex,
    embed: Option<TensorIndex>,
    config_path: PathBuf,
    processor_path: PathBuf,
    statistics_path: PathBuf,
    embodiment_id_path: PathBuf,
    model_name: String,
}

fn plan(ckpt: &Path, opts: &ImportOptions) -> Result<Plan> {
    if !ckpt.is_dir() {
        return Err(err(ckpt, "(directory)", "is not a directory"));
    }
    // ---- config.json ----
    let config_path = ckpt.join(CONFIG_FILE);
    let config = read_json(&config_path)?;
    let c = At::root(&config, &config_path, "");
    if let Some(t) = c.opt("model_type")? {
        let t = t.str()?;
        if t != "Gr00tN1d7" {
            return Err(c.key("model_type")?.err(format!(
                "is `{t}`; pir2 imports GR00T N1.7 checkpoints (`Gr00tN1d7`)"
            )));
        }
    }
    let cfg = Gr00tN17Config::from_json_file(&config_path).map_err(|e| from_head(e, ckpt))?;

    // ---- processor_config.json ----
    let processor_path = processor_file(ckpt, PROCESSOR_FILE);
    let processor = read_json(&processor_path)?;
    let p = At::root(&processor, &processor_path, "");
    if let Some(cls) = p.opt("processor_class")? {
        let s = cls.str()?;
        if s != "Gr00tN1d7Processor" {
            return Err(cls.err(format!(
                "is `{s}`; pir2 imports GR00T N1.7's processor (`Gr00tN1d7Processor`)"
            )));
        }
    }
    let kw = p.key("processor_kwargs")?;
    kw.only(PROCESSOR_KWARGS, "Gr00tN1d7Processor.save_pretrained")?;
    let flag = |k: &str, default: bool| -> Result<bool> {
        match kw.opt(k)? {
            None => Ok(default),
            Some(a) => a.bool(),
        }
    };
    let refuse_true = |k: &str, why: &str| -> Result<()> {
        if flag(k, false)? {
            return Err(kw.key(k)?.err(format!("is true; {why}")));
        }
        Ok(())
    };
    refuse_true(
        "exclude_state",
        "the state is zeroed in this checkpoint; pir2 always feeds the robot state",
    )?;
    refuse_true(
        "use_tactile",
        "pir2 has no tactile encoder (the pressure groups would need GR00T's tactile CNN)",
    )?;
    refuse_true(
        "use_mean_std",
        "Isaac-GR00T's StateActionProcessor picks mean/std per group \
         (`mean_std_embedding_keys`), and pir2 does not guess a global meaning for this flag",
    )?;
    if !flag("clip_outliers", true)? {
        return Err(kw.key("clip_outliers")?.err(
            "is false; pir2's normaliser clips min/max and percentile groups to [-1, 1] as \
             GR00T's default does",
        ));
    }
    let use_percentiles = flag("use_percentiles", false)?;
    let sincos = flag("apply_sincos_state_encoding", false)?;
    let use_relative = flag("use_relative_action", false)?;
    let model_name = match kw.opt("model_name")? {
        None => N17_VLM.to_string(),
        Some(a) => a.str()?.to_string(),
    };
    if model_name != N17_VLM {
        return Err(kw.key("model_name")?.err(format!(
            "is `{model_name}`; pir2's prompt template and vision patching are {N17_VLM}'s \
             (GR00T N1.7's VLM)"
        )));
    }
    if let Some(t) = kw.opt("model_type")? {
        if t.str()? != "qwen" {
            return Err(t.err(format!("is `{}`; GR00T N1.7's is `qwen`", t.str()?)));
        }
    }
    // Image pipeline (albumentations' eval transform).
    if !flag("use_albumentations", false)? {
        return Err(err(
            &processor_path,
            "processor_kwargs.use_albumentations",
            "is false or missing: the checkpoint uses the torchvision pipeline, which pir2 \
             does not implement (pir2 implements N1.7's albumentations pipeline: letterbox, \
             SmallestMaxSize with INTER_AREA, centre crop, resize)",
        ));
    }
    let pair = |k: &str| -> Result<Option<(u64, u64)>> {
        match kw.opt(k)? {
            None => Ok(None),
            Some(a) => {
                let v = a.items()?;
                if v.len() != 2 {
                    return Err(a.err("must be [height, width]"));
                }
                Ok(Some((v[0].u64()?, v[1].u64()?)))
            }
        }
    };
    let shortest_edge = match kw.opt("shortest_image_edge")? {
        Some(a) => a.u64()? as usize,
        None => {
            return Err(err(
                &processor_path,
                "processor_kwargs.shortest_image_edge",
                "is null: the checkpoint resizes to `image_target_size` without keeping the \
                 aspect ratio, which pir2 does not implement",
            ))
        }
    };
    let crop_fraction = match kw.opt("crop_fraction")? {
        Some(a) => a.f64()?,
        None => match (pair("image_crop_size")?, pair("image_target_size")?) {
            (Some((c, _)), Some((t, _))) if t > 0 => c as f64 / t as f64,
            _ => {
                return Err(err(
                    &processor_path,
                    "processor_kwargs.crop_fraction",
                    "is null and `image_crop_size` / `image_target_size` do not give it",
                ))
            }
        },
    };
    // Read (and type-checked) but not mapped: N1.7's processor stores
    // `letter_box_transform` and never reads it; its albumentations eval pipeline pads every
    // frame to a square (`image_augmentations.py`, `build_image_transformations_albumentations`),
    // so the imported embodiment letterboxes whatever the flag says.
    let _stored_not_read = flag("letter_box_transform", false)?;
    let letterbox = true;
    let formalize = flag("formalize_language", true)?;

    // ---- the embodiment ----
    let mcs = kw.key("modality_configs")?;
    let tags: Vec<String> = mcs.obj()?.keys().cloned().collect();
    let tag = match &opts.embodiment_tag {
        Some(t) => t.clone(),
        None if tags.len() == 1 => tags[0].clone(),
        None => {
            return Err(mcs.err(format!(
                "has {} embodiments ({}); choose one with --embodiment-tag",
                tags.len(),
                tags.join(", ")
            )))
        }
    };
    let Some(mc) = mcs.opt(&tag)? else {
        return Err(err(
            &processor_path,
            format!("processor_kwargs.modality_configs.{tag}"),
            format!(
                "unknown embodiment tag; the checkpoint has: {}",
                tags.join(", ")
            ),
        ));
    };
    mc.only(
        &["video", "state", "action", "language"],
        "an embodiment's modality configs",
    )?;
    let video = modality(&mc.key("video")?)?;
    let state = modality(&mc.key("state")?)?;
    let action = modality(&mc.key("action")?)?;

    // Horizons.
    let h = action.delta_indices.len();
    if action.delta_indices != (0..h as i64).collect::<Vec<_>>() {
        return Err(mc.key("action")?.key("delta_indices")?.err(format!(
            "is {:?}; pir2 runs chunks of consecutive actions from the current step (0, 1, …, H−1)",
            action.delta_indices
        )));
    }
    let n_obs = state.delta_indices.len();
    let consecutive = state.delta_indices.last() == Some(&0)
        && state.delta_indices.windows(2).all(|w| w[1] == w[0] + 1);
    if !consecutive {
        return Err(mc.key("state")?.key("delta_indices")?.err(format!(
            "is {:?}; pir2 feeds the last n_obs consecutive states ending at 0",
            state.delta_indices
        )));
    }
    if video.delta_indices != [0] {
        return Err(mc.key("video")?.key("delta_indices")?.err(format!(
            "is {:?}; pir2 feeds one frame per camera view (the current one, [0])",
            video.delta_indices
        )));
    }
    if let Some(x) = mc
        .opt("video")?
        .and_then(|v| v.opt("sin_cos_embedding_keys").ok()?)
    {
        return Err(x.err("is set for video; it is a state encoding"));
    }
    if !action.sin_cos.is_empty() {
        return Err(mc
            .key("action")?
            .key("sin_cos_embedding_keys")?
            .err("is set for actions; sin/cos is a state encoding (it cannot be decoded)"));
    }

    // ---- statistics.json ----
    let statistics_path = processor_file(ckpt, STATISTICS_FILE);
    let statistics = read_json(&statistics_path)?;
    let st_root = At::root(&statistics, &statistics_path, "");
    let Some(stats) = st_root.opt(&tag)? else {
        let have: Vec<String> = st_root.obj()?.keys().cloned().collect();
        return Err(err(
            &statistics_path,
            tag.clone(),
            format!(
                "unknown embodiment tag: no statistics for it (the file has: {})",
                have.join(", ")
            ),
        ));
    };
    let minmax_stat = if use_percentiles { "q01" } else { "min" };
    let mut state_groups = Vec::new();
    for k in &state.keys {
        let (norm, stat) = if sincos && state.sin_cos.contains(k) {
            (Norm::SinCos, minmax_stat)
        } else {
            norm_and_width_stat(state.mean_std.contains(k), use_percentiles, minmax_stat)
        };
        let dim = stat_width(&stats, "state", k, stat)?;
        let mut g = Group::new(k, dim);
        g.norm = norm;
        state_groups.push(g);
    }
    let mut action_groups = Vec::new();
    let af = mc.key("action")?;
    for (i, k) in action.keys.iter().enumerate() {
        let (norm, stat) =
            norm_and_width_stat(action.mean_std.contains(k), use_percentiles, minmax_stat);
        // GR00T takes a group's width from its absolute statistics, also for relative groups.
        let dim = stat_width(&stats, "action", k, stat)?;
        let mut g = Group::new(k, dim);
        g.norm = norm;
        if let Some(cfgs) = &action.actions {
            let (rep, ty, format, state_key) = &cfgs[i];
            let field = |f: &str| format!("{}.action_configs[{i}].{f}", af.field);
            match rep.as_str() {
                "ABSOLUTE" => {}
                "RELATIVE" if !use_relative => {}
                "RELATIVE" => {
                    g.relative = true;
                    g.state_key = state_key.clone();
                    g.format = match (ty.as_str(), format.as_str()) {
                        ("NON_EEF", "DEFAULT") => GroupFormat::Default,
                        ("EEF", "XYZ_ROT6D") => GroupFormat::XyzRot6d,
                        ("EEF", "XYZ_ROTVEC") => GroupFormat::XyzRotvec,
                        ("NON_EEF" | "EEF", f) => {
                            return Err(err(
                                &processor_path,
                                field("format"),
                                format!(
                                    "is `{f}` with type `{ty}`; pir2 maps NON_EEF + DEFAULT \
                                     (joints), EEF + XYZ_ROT6D and EEF + XYZ_ROTVEC (poses)"
                                ),
                            ))
                        }
                        (t, _) => {
                            return Err(err(
                                &processor_path,
                                field("type"),
                                format!("is `{t}`; GR00T's ActionType is EEF or NON_EEF"),
                            ))
                        }
                    };
                }
                "DELTA" => {
                    return Err(err(
                        &processor_path,
                        field("rep"),
                        "is DELTA; pir2 decodes absolute and relative action groups, not \
                         deltas",
                    ))
                }
                other => {
                    return Err(err(
                        &processor_path,
                        field("rep"),
                        format!(
                        "is `{other}`; GR00T's ActionRepresentation is ABSOLUTE, RELATIVE or DELTA"
                    ),
                    ))
                }
            }
        }
        action_groups.push(g);
    }

    // ---- embodiment_id.json ----
    let embodiment_id_path = processor_file(ckpt, EMBODIMENT_ID_FILE);
    let ids = read_json(&embodiment_id_path)?;
    let ids_at = At::root(&ids, &embodiment_id_path, "");
    let Some(id_at) = ids_at.opt(&tag)? else {
        let have: Vec<String> = ids_at.obj()?.keys().cloned().collect();
        return Err(err(
            &embodiment_id_path,
            tag.clone(),
            format!(
                "unknown embodiment tag: no slot for it (the file maps: {})",
                have.join(", ")
            ),
        ));
    };
    let embodiment_id = id_at.u64()? as i64;
    if embodiment_id as usize >= cfg.max_num_embodiments {
        return Err(id_at.err(format!(
            "is {embodiment_id}, outside the head's {} slots (config.json max_num_embodiments)",
            cfg.max_num_embodiments
        )));
    }

    // ---- the embodiment file ----
    let images = video.keys.len();
    let mut emb = EmbodimentConfig::xarm6_xhand();
    emb.name = format!("gr00t-{tag}");
    emb.embodiment_tag = tag.clone();
    emb.embodiment_id = embodiment_id;
    emb.control_hz = opts.control_hz;
    emb.horizon = h;
    emb.d_max = emb.d_max.min(h.saturating_sub(1));
    emb.n_obs = n_obs;
    emb.num_timestep_buckets = cfg.num_timestep_buckets as i64;
    emb.cameras = Vec::new();
    emb.state = state_groups;
    emb.action = action_groups;
    emb.tasks = BTreeMap::new();
    emb.image.pipeline = ImagePipeline::Gr00tN17;
    emb.image.letterbox = letterbox;
    emb.image.shortest_edge = shortest_edge;
    emb.image.crop_fraction = crop_fraction;
    let per_side = shortest_edge / (emb.vision.patch_size * emb.vision.merge_size);
    emb.prompt.image_tokens = images * per_side * per_side;
    emb.prompt.chat.images = images;
    emb.prompt.chat.formalize_language = formalize;
    emb.policy.trained = pir2_runtime::Policy::Flow;
    emb.policy.flow_steps = cfg.num_inference_timesteps.max(1);
    emb.policy.mode = super::config::DeployKind::SyncFlow;
    emb.policy.h = emb.policy.h.min(h).max(1);
    emb.validate().map_err(|e| match e {
        Gr00tError::Config(m) => err(
            &processor_path,
            format!("processor_kwargs.modality_configs.{tag}"),
            format!("does not make a valid pir2 embodiment: {m}"),
        ),
        other => other,
    })?;

    // ---- the head fits ----
    let size = |k: &str| -> Result<Option<usize>> {
        Ok(match kw.opt(k)? {
            None => None,
            Some(a) => Some(a.u64()? as usize),
        })
    };
    for (k, mine) in [
        ("max_state_dim", cfg.max_state_dim),
        ("max_action_dim", cfg.max_action_dim),
    ] {
        if let Some(v) = size(k)? {
            if v != mine {
                return Err(kw.key(k)?.err(format!(
                    "is {v}, config.json's `{k}` is {mine}; the two files are not of one checkpoint"
                )));
            }
        }
    }
    if emb.encoded_state_dim() > cfg.max_state_dim {
        return Err(err(
            &statistics_path,
            format!("{tag}.state"),
            format!(
                "the state groups are {} values wide (sin/cos doubled), over config.json's \
                 max_state_dim = {}",
                emb.encoded_state_dim(),
                cfg.max_state_dim
            ),
        ));
    }
    if emb.action_dim() > cfg.max_action_dim {
        return Err(err(
            &statistics_path,
            format!("{tag}.action"),
            format!(
                "the action groups are {} values wide, over config.json's max_action_dim = {}",
                emb.action_dim(),
                cfg.max_action_dim
            ),
        ));
    }
    if h > cfg.action_horizon {
        return Err(af.key("delta_indices")?.err(format!(
            "gives H = {h}, over config.json's action_horizon = {}",
            cfg.action_horizon
        )));
    }
    if n_obs != cfg.state_history_length {
        return Err(mc.key("state")?.key("delta_indices")?.err(format!(
            "gives {n_obs} state steps; config.json's state_history_length is {}",
            cfg.state_history_length
        )));
    }
    // Every statistic each group's norm needs, with the group's width.
    Normalizer::load(&statistics_path, &emb)?;

    // ---- the weights ----
    let weights_src = if ckpt.join(INDEX_FILE).is_file() {
        ckpt.join(INDEX_FILE)
    } else if ckpt.join(SINGLE_FILE).is_file() {
        ckpt.join(SINGLE_FILE)
    } else {
        return Err(err(
            ckpt,
            SINGLE_FILE,
            format!("is missing, and so is {INDEX_FILE} (the sharded form)"),
        ));
    };
    if weights_src.ends_with(INDEX_FILE) {
        // Every shard the index names must be there (one error naming the first missing).
        let v = read_json(&weights_src)?;
        let map = At::root(&v, &weights_src, "");
        for (name, file) in map.key("weight_map")?.obj()? {
            let f = file.as_str().unwrap_or_default();
            if !ckpt.join(f).is_file() {
                return Err(err(
                    &weights_src,
                    format!("weight_map.{name}"),
                    format!("names the shard `{f}`, which is not in the directory"),
                ));
            }
        }
    }
    let index = TensorIndex::open(&weights_src, PREFIX).map_err(|e| from_head(e, ckpt))?;
    if index.names().next().is_none() {
        return Err(err(
            &weights_src,
            format!("{PREFIX}*"),
            "no action-head tensor in the checkpoint",
        ));
    }
    let embed =
        TensorIndex::open(&weights_src, EMBED_TOKENS_KEY).map_err(|e| from_head(e, ckpt))?;
    let embed = embed.contains(EMBED_TOKENS_KEY).then_some(embed);
    Ok(Plan {
        cfg,
        emb,
        tag,
        index,
        embed,
        config_path,
        processor_path,
        statistics_path,
        embodiment_id_path,
        model_name,
    })
}

/// GR00T's normalisation of a non-sin/cos group (mean/std where the modality config lists
/// it, else q01/q99 with percentiles, else min/max) and the statistic its width is read from.
fn norm_and_width_stat(
    mean_std: bool,
    use_percentiles: bool,
    minmax_stat: &'static str,
) -> (Norm, &'static str) {
    if mean_std {
        (Norm::MeanStd, "mean")
    } else if use_percentiles {
        (Norm::Q01Q99, minmax_stat)
    } else {
        (Norm::MinMax, minmax_stat)
    }
}

/// Write the tensors `names` of the indices to one safetensors file, bytes copied from their
/// sources as stored (no conversion).
fn write_safetensors(out: &Path, tensors: &[(&TensorIndex, String)]) -> Result<()> {
    let io = |source| Gr00tError::Read {
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
    let mut h = serde_json::to_vec(&Value::Object(header)).map_err(|e| Gr00tError::Parse {
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
        let mut src = File::open(&file).map_err(|source| Gr00tError::Read {
            path: file.clone(),
            source,
        })?;
        src.seek(SeekFrom::Start(start))
            .map_err(|source| Gr00tError::Read {
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
    std::fs::copy(from, to).map_err(|source| Gr00tError::Read {
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
                .map_err(|source| Gr00tError::Read {
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
    // GR00T's head with a zero delay table: what the released head computes.
    let head = Gr00tN17Head::trainable_from_index(
        &plan.index,
        plan.cfg.clone(),
        plan.emb.d_vis_max,
        &device,
    )
    .map_err(|e| from_head(e, ckpt))?;
    let export = super::n17::export::export_gr00t_n17(&head, plan.emb.horizon).map_err(|e| {
        Gr00tError::Candle {
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
        move |source| Gr00tError::Read { path, source }
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
            .write(&tmp, super::n17::export::WeightStorage::Auto)
            .map_err(|e| Gr00tError::Candle {
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
                        super::onnx_f32::copy_onnx(src, &dst)?
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
