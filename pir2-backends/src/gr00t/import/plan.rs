//! The mapping: Isaac-GR00T's configuration files (`config.json`, `processor_config.json`,
//! `statistics.json`, `embodiment_id.json`) and weight index read, checked field by field and
//! turned into our embodiment configuration and the tensors to copy ([`Plan`]), before
//! anything is written. The per-group normalisation GR00T applies, and the statistics the
//! group widths are read from, are decided here too.

use std::collections::BTreeMap;

use std::path::{Path, PathBuf};

use serde_json::Value;

use super::read::{
    err, from_head, processor_file, read_json, At, CONFIG_FILE, EMBODIMENT_ID_FILE, PROCESSOR_FILE,
    STATISTICS_FILE,
};
use crate::error::{Error, Result};
use crate::gr00t::config::{
    EmbodimentConfig, Group, GroupFormat, ImagePipeline, Norm, Normalizer, EMBED_TOKENS_KEY,
};
use crate::gr00t::n17::{
    Gr00tN17Config, TensorIndex, DELAY_EMBEDDING, INDEX_FILE, PREFIX, SINGLE_FILE,
};

/// The VLM the prompt and vision defaults of pir2 are those of (GR00T N1.7's default
/// `model_name`).
pub const N17_VLM: &str = "nvidia/Cosmos-Reason2-2B";

/// Options of [`import_checkpoint`](super::import_checkpoint).
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
    /// What the head was fine-tuned as (`[policy] trained`); `None`: `pi_r2` for a head
    /// with per-position AdaLN heads (πR²'s architecture), `flow` for one without (GR00T's).
    /// A head with per-position heads declared `flow` or `rtc` is refused: the baselines keep
    /// the shared modulation.
    pub trained: Option<pir2_runtime::Policy>,
    /// πR² NFEs per action (`[policy] nfe`); `None`: the [`PolicySection`] default (2), or
    /// the largest `n` the staircase allows when that is smaller. Must fit the fresh
    /// staircase at the imported `H` and `d_max`; refused for policies without an `n`
    /// (`flow`, `rtc`, `pi_r2_full`, `pi_r2_zero_delay_full`).
    ///
    /// [`PolicySection`]: crate::gr00t::config::PolicySection
    pub nfe: Option<usize>,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            embodiment_tag: None,
            backbone_onnx: None,
            keep_bf16: false,
            control_hz: 25.0,
            trained: None,
            nfe: None,
        }
    }
}

/// `(rep, type, format, state_key)` of an `ActionConfig`, enum names as GR00T writes them.
type ActionCfg = (String, String, String, Option<String>);

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
pub(super) struct Plan {
    pub(super) cfg: Gr00tN17Config,
    pub(super) emb: EmbodimentConfig,
    pub(super) tag: String,
    pub(super) index: TensorIndex,
    pub(super) embed: Option<TensorIndex>,
    pub(super) config_path: PathBuf,
    pub(super) processor_path: PathBuf,
    pub(super) statistics_path: PathBuf,
    pub(super) embodiment_id_path: PathBuf,
    pub(super) model_name: String,
}

pub(super) fn plan(ckpt: &Path, opts: &ImportOptions) -> Result<Plan> {
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
    // The largest delay (at most the default 5, below H) every policy can be fine-tuned
    // for: πR²'s fresh staircase needs H ≥ 3·d − 1, so a short chunk takes a smaller d_max.
    let fits = |d: usize| {
        pir2_schedule::Staircase::new(h, d, None, pir2_schedule::Alignment::Fresh).is_ok()
    };
    emb.d_max = (1..=emb.d_max.min(h.saturating_sub(1)))
        .rev()
        .find(|&d| fits(d))
        .unwrap_or(emb.d_max.min(h.saturating_sub(1)));
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
    emb.policy.flow_steps = cfg.num_inference_timesteps.max(1);
    emb.policy.h = emb.policy.h.min(h).max(1);
    emb.validate().map_err(|e| match e {
        Error::Gr00tConfig(m) => err(
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

    // ---- the weights, and what they say about the head ----
    let weights_src = weights_source(ckpt)?;
    let index = TensorIndex::open(&weights_src, PREFIX).map_err(|e| from_head(e, ckpt))?;
    if index.names().next().is_none() {
        return Err(err(
            &weights_src,
            format!("{PREFIX}*"),
            "no action-head tensor in the checkpoint",
        ));
    }
    let heads = position_heads(&index, &cfg, h)?;
    if let Some(shape) = index.shape(&format!("{PREFIX}{DELAY_EMBEDDING}")) {
        // πR²'s delay table: its rows say the largest slow-feature age it was trained for.
        if let Some(&rows) = shape.first() {
            if rows >= 1 {
                emb.d_vis_max = rows - 1;
            }
        }
    }
    set_policy(&mut emb, opts, heads, &weights_src)?;
    emb.validate().map_err(|e| match e {
        Error::Gr00tConfig(m) => err(
            &weights_src,
            "[policy] / delay_embedding",
            format!("does not make a valid pir2 embodiment: {m}"),
        ),
        other => other,
    })?;
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

/// The checkpoint's weights: `model.safetensors.index.json` (every shard it names must be
/// there) or `model.safetensors`.
fn weights_source(ckpt: &Path) -> Result<PathBuf> {
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
    Ok(weights_src)
}

/// Whether the head's AdaLN modulations are πR²'s per-position heads: every block's
/// `norm1.linear` and `proj_out_1` as `<layer>_heads.{weight [1 + H, out, in], bias [1 + H,
/// out]}` (`true`), or every one as GR00T's shared `<layer>.{weight, bias}` (`false`). A mix,
/// or heads whose count is not `1 + H` (`h`: the imported horizon), is one error naming the
/// tensor and the file.
fn position_heads(index: &TensorIndex, cfg: &Gr00tN17Config, h: usize) -> Result<bool> {
    let mut layers: Vec<String> = (0..cfg.dit.num_layers)
        .map(|i| format!("model.transformer_blocks.{i}.norm1.linear"))
        .filter(|l| {
            index.contains(&format!("{PREFIX}{l}.weight"))
                || index.contains(&format!("{PREFIX}{l}_heads.weight"))
        })
        .collect();
    layers.push("model.proj_out_1".to_string());
    // The file holding a tensor (its shard when the checkpoint is sharded).
    let file = |name: &str| -> PathBuf {
        index
            .location(name)
            .map_or_else(|| index.source().to_path_buf(), |l| l.0.to_path_buf())
    };
    let with: Vec<&String> = layers
        .iter()
        .filter(|l| index.contains(&format!("{PREFIX}{l}_heads.weight")))
        .collect();
    if with.is_empty() {
        return Ok(false);
    }
    if let Some(shared) = layers
        .iter()
        .find(|l| !index.contains(&format!("{PREFIX}{l}_heads.weight")))
    {
        let name = format!("{PREFIX}{shared}.weight");
        return Err(err(
            &file(&name),
            name,
            format!(
                "is GR00T's shared modulation, but `{PREFIX}{}_heads.weight` is per-position: \
                 a πR² head has per-position heads for every AdaLN layer (each block's \
                 norm1.linear and proj_out_1) or for none",
                with[0]
            ),
        ));
    }
    for l in &layers {
        for k in ["weight", "bias"] {
            let name = format!("{PREFIX}{l}_heads.{k}");
            let Some(shape) = index.shape(&name) else {
                return Err(err(
                    index.source(),
                    name,
                    "is missing (the `_heads.weight` is there)",
                ));
            };
            let n = shape.first().copied().unwrap_or(0);
            if n != 1 + h {
                return Err(err(
                    &file(&name),
                    name,
                    format!(
                        "has {n} per-position heads, but the imported horizon H = {h} (the \
                         action delta_indices) needs 1 + H = {} (the state token and H actions)",
                        1 + h
                    ),
                ));
            }
        }
    }
    Ok(true)
}

/// `[policy]` of the imported embodiment: `trained` (the request, else `pi_r2` for a head with
/// per-position heads and `flow` without), the matching default `mode`, and `nfe` checked
/// against the fresh staircase at the embodiment's `H` and `d_max`.
fn set_policy(
    emb: &mut EmbodimentConfig,
    opts: &ImportOptions,
    heads: bool,
    weights: &Path,
) -> Result<()> {
    use crate::gr00t::config::{policy_name, DeployKind};
    use pir2_runtime::Policy as P;
    let trained = match opts.trained {
        Some(p) => p,
        None if heads => P::PiR2,
        None => P::Flow,
    };
    if heads && !trained.per_position_heads() {
        return Err(err(
            weights,
            "--trained",
            format!(
                "is `{}`, but the head has per-position AdaLN heads \
                 (`{PREFIX}model.proj_out_1_heads.weight`), πR²'s architecture; the `{}` \
                 baseline keeps GR00T's shared modulation",
                policy_name(trained),
                policy_name(trained)
            ),
        ));
    }
    let h = emb.horizon;
    let staircase_d = match trained {
        P::PiR2 | P::PiR2Hidden => Some(emb.d_max),
        P::PiR2ZeroDelay => Some(0),
        P::PiR2Full | P::PiR2ZeroDelayFull | P::Flow | P::Rtc => None,
    };
    let nfe = match (staircase_d, opts.nfe) {
        (None, Some(n)) => {
            return Err(err(
                weights,
                "--nfe",
                format!(
                    "is {n}, but a `{}` head has no πR² n to set",
                    policy_name(trained)
                ),
            ))
        }
        (None, None) => emb.policy.nfe,
        (Some(d), n) => {
            // Unset: the section's default, at most the largest n the staircase allows.
            let n = n.unwrap_or_else(|| {
                emb.policy
                    .nfe
                    .min(pir2_schedule::Staircase::n_max(h, d))
                    .max(1)
            });
            let fits =
                pir2_schedule::Staircase::new(h, d, Some(n), pir2_schedule::Alignment::Fresh);
            if let Err(e) = fits {
                return Err(err(
                    weights,
                    "--nfe",
                    format!(
                        "is {n}, which does not fit πR²'s staircase at H = {h}, d_max = {d}: {e}"
                    ),
                ));
            }
            n
        }
    };
    emb.policy.trained = trained;
    emb.policy.nfe = nfe;
    emb.policy.mode = match trained {
        P::Flow => DeployKind::SyncFlow,
        P::Rtc => DeployKind::Rtc,
        _ => DeployKind::PiR2Async,
    };
    Ok(())
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
