//! `pir2 gr00t import` through the binary, on synthetic GR00T N1.7 checkpoints whose every
//! file follows the schema Isaac-GR00T writes, at tiny sizes; then the imported head loaded
//! and run one NFE, compared to the same weights loaded straight from the GR00T directory;
//! and bad or partial directories, each one error naming the file and the field.
//!
//! The schema, from NVIDIA/Isaac-GR00T (file @ commit, lines):
//! - `processor_config.json`, `statistics.json`, `embodiment_id.json`:
//!   `Gr00tN1d7Processor.save_pretrained`, `gr00t/model/gr00t_n1d7/processing_gr00t_n1d7.py`
//!   @ 1852a8c13382b25cb656331b660600859925cfa0, `save_pretrained` (`processor_class`,
//!   `processor_kwargs` with `modality_configs` and the image, VLM, dimension and
//!   normalisation settings; statistics `{tag: {modality: {group: {stat: [..]}}}}`;
//!   `{tag: slot}`), and the projector slots of the released tags,
//!   `_PROJECTOR_INDEX_GROUPS` (`new_embodiment` → 10, `libero_sim` → 2);
//! - the modality configs: `ModalityConfig` / `ActionConfig` serialised with
//!   `dataclasses.asdict` and enums by name, `gr00t/data/types.py` @
//!   be889e7a1ac76a409eaca575a5139338e41dedfc (`ModalityConfig`, `ActionConfig`),
//!   `gr00t/data/utils.py` @ 066d167414aed0c97541274fdb1b06ff36564868
//!   (`to_json_serializable`);
//! - relative-action statistics `relative_action.<group>` replacing `action.<group>`:
//!   `gr00t/data/state_action/state_action_processor.py` @
//!   98a45fe6604c96ff2244750473aeee6efb43b08b (`_compute_normalization_parameters`);
//! - `config.json`: `Gr00tN1d7Config`, `gr00t/configs/model/gr00t_n1d7.py` @
//!   543b45271898211a63f5bf5e03633316bd6189f5, class `Gr00tN1d7Config` (`model_type = "Gr00tN1d7"`,
//!   `diffusion_model_cfg`);
//! - the released file set (`config.json`, `embodiment_id.json`, `model-*.safetensors`,
//!   `model.safetensors.index.json`, `processor_config.json`, `statistics.json`):
//!   `scripts/deployment/README.md` @ 1ca4b07087c8497c75aecf072dd95519f23726c2, the
//!   `hf download --include` list of "Step 0";
//! - the action head's tensor names (`action_head.state_encoder.layer1.W`, …): those pir2's
//!   N1.7 loader reads (`pir2_backends::gr00t::n17::head_tensor_shapes`, checked against
//!   NVIDIA's reference fixtures in `pir2-backends/tests/gr00t_n17_head.rs`).
#![cfg(feature = "gr00t")]

use std::collections::HashMap;
use std::ffi::OsStr;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use pir2_backends::gr00t::config::Norm;
use pir2_backends::gr00t::n17::{
    head_tensor_shapes, Gr00tN17Config, Gr00tN17Head, Timesteps, VlTokens, PREFIX,
};
use pir2_backends::gr00t::{EmbodimentConfig, GroupFormat, EMBED_TOKENS_KEY};
use serde_json::{json, Value};

mod common;
use common::gr00t::candle_on_recorded_call;
use common::gr00t::pir2_text as pir2;
use common::Scratch;

const H: usize = 8;
const D_VL: usize = 8;
const TAG: &str = "new_embodiment";

fn config_json() -> Value {
    json!({
        "model_type": "Gr00tN1d7",
        "model_dtype": "bfloat16",
        "model_name": "nvidia/Cosmos-Reason2-2B",
        "backbone_model_type": "qwen",
        "select_layer": 12,
        "action_horizon": H,
        "add_pos_embed": true,
        "attend_text_every_n_blocks": 2,
        "backbone_embedding_dim": D_VL,
        "diffusion_model_cfg": {
            "positional_embeddings": null,
            "num_layers": 2,
            "num_attention_heads": 2,
            "attention_head_dim": 4,
            "norm_type": "ada_norm",
            "dropout": 0.2,
            "final_dropout": true,
            "output_dim": 12,
            "interleave_self_attention": true
        },
        "hidden_size": 12,
        "input_embedding_dim": 8,
        "max_action_dim": 12,
        "max_num_embodiments": 12,
        "max_seq_len": 16,
        "max_state_dim": 16,
        "num_inference_timesteps": 4,
        "num_timestep_buckets": 1000,
        "state_history_length": 1,
        "use_alternate_vl_dit": true,
        "use_vlln": true,
        "use_percentiles": true,
        "use_relative_action": true
    })
}

/// State: `arm` 3 (min/max via percentiles), `wrist` 2 (sin/cos), `force` 2 (mean/std);
/// action: `arm` 3 relative to the state `arm`, `gripper` 1 absolute.
fn processor_json() -> Value {
    let modality = json!({
        "video": {"delta_indices": [0], "modality_keys": ["ego_view"],
                  "sin_cos_embedding_keys": null, "mean_std_embedding_keys": null,
                  "action_configs": null},
        "state": {"delta_indices": [0], "modality_keys": ["arm", "wrist", "force"],
                  "sin_cos_embedding_keys": ["wrist"], "mean_std_embedding_keys": ["force"],
                  "action_configs": null},
        "action": {"delta_indices": (0..H).collect::<Vec<_>>(),
                   "modality_keys": ["arm", "gripper"],
                   "sin_cos_embedding_keys": null, "mean_std_embedding_keys": null,
                   "action_configs": [
                       {"rep": "RELATIVE", "type": "NON_EEF", "format": "DEFAULT", "state_key": "arm"},
                       {"rep": "ABSOLUTE", "type": "NON_EEF", "format": "DEFAULT", "state_key": null}
                   ]},
        "language": {"delta_indices": [0], "modality_keys": ["annotation.human.task_description"],
                     "sin_cos_embedding_keys": null, "mean_std_embedding_keys": null,
                     "action_configs": null}
    });
    json!({
        "processor_class": "Gr00tN1d7Processor",
        "processor_kwargs": {
            "modality_configs": {TAG: modality},
            "image_crop_size": null,
            "image_target_size": null,
            "use_albumentations": true,
            "random_rotation_angle": null,
            "color_jitter_params": {"brightness": 0.3, "contrast": 0.4, "saturation": 0.5, "hue": 0.08},
            "shortest_image_edge": 256,
            "crop_fraction": 0.95,
            "letter_box_transform": true,
            "model_name": "nvidia/Cosmos-Reason2-2B",
            "model_type": "qwen",
            "formalize_language": true,
            "max_state_dim": 16,
            "max_action_dim": 12,
            "max_action_horizon": H,
            "use_percentiles": true,
            "use_mean_std": false,
            "clip_outliers": true,
            "apply_sincos_state_encoding": true,
            "use_relative_action": true,
            "exclude_state": false,
            "state_dropout_prob": 0.0
        }
    })
}

fn stats(dim: usize, rows: Option<usize>, lo: f64) -> Value {
    let v = |x: f64| -> Value {
        let row: Vec<f64> = (0..dim).map(|i| x + 0.1 * i as f64).collect();
        match rows {
            None => json!(row),
            Some(r) => json!(vec![row; r]),
        }
    };
    json!({"min": v(lo), "max": v(lo + 2.0), "mean": v(lo + 1.0), "std": v(0.5),
           "q01": v(lo + 0.1), "q99": v(lo + 1.9)})
}

fn statistics_json() -> Value {
    json!({TAG: {
        "state": {"arm": stats(3, None, -1.0), "wrist": stats(2, None, -3.0), "force": stats(2, None, 0.0)},
        "action": {"arm": stats(3, None, -1.0), "gripper": stats(1, None, 0.0)},
        "relative_action": {"arm": stats(3, Some(H), -0.2)}
    }})
}

/// The head's tensors with random values, plus two backbone tensors (the token table,
/// which the import keeps, and one it does not).
fn tensors(cfg: &Gr00tN17Config, dtype: DType) -> Vec<(String, Tensor)> {
    let mut rng = pir2_schedule::Rng::new(23);
    let mut out = Vec::new();
    let mut shapes: Vec<(String, Vec<usize>)> = head_tensor_shapes(cfg)
        .into_iter()
        .map(|(n, s)| (format!("{PREFIX}{n}"), s))
        .collect();
    shapes.push((EMBED_TOKENS_KEY.to_string(), vec![20, D_VL]));
    shapes.push((
        "backbone.model.visual.patch_embed.proj.weight".into(),
        vec![4, 6],
    ));
    for (name, shape) in shapes {
        let n: usize = shape.iter().product();
        let fan_in = if shape.len() >= 2 {
            shape[shape.len() - 2]
        } else {
            1
        };
        let s = 1.0 / (fan_in as f32).sqrt();
        let v: Vec<f32> = (0..n).map(|_| rng.uniform_range(-s, s)).collect();
        let t = Tensor::from_vec(v, shape, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        out.push((name, t));
    }
    out
}

/// A GR00T N1.7 checkpoint directory: single `model.safetensors` (F32) or two BF16 shards
/// with `model.safetensors.index.json`.
fn gr00t_checkpoint(dir: &Path, sharded: bool) {
    std::fs::create_dir_all(dir).unwrap();
    let write = |name: &str, v: &Value| {
        std::fs::write(dir.join(name), serde_json::to_string_pretty(v).unwrap()).unwrap()
    };
    write("config.json", &config_json());
    write("processor_config.json", &processor_json());
    write("statistics.json", &statistics_json());
    write(
        "embodiment_id.json",
        &json!({"simpler_env_google": 0, "simpler_env_widowx": 1, "libero_sim": 2, TAG: 10}),
    );
    let cfg = Gr00tN17Config::from_json_file(&dir.join("config.json")).unwrap();
    if !sharded {
        let map: HashMap<String, Tensor> = tensors(&cfg, DType::F32).into_iter().collect();
        candle_core::safetensors::save(&map, dir.join("model.safetensors")).unwrap();
        return;
    }
    let all = tensors(&cfg, DType::BF16);
    let half = all.len() / 2;
    let mut weight_map = serde_json::Map::new();
    for (k, part) in [&all[..half], &all[half..]].iter().enumerate() {
        let file = format!("model-0000{}-of-00002.safetensors", k + 1);
        let map: HashMap<String, Tensor> = part.iter().cloned().collect();
        candle_core::safetensors::save(&map, dir.join(&file)).unwrap();
        for (n, _) in part.iter() {
            weight_map.insert(n.clone(), json!(file));
        }
    }
    write(
        "model.safetensors.index.json",
        &json!({"metadata": {"total_size": 0}, "weight_map": weight_map}),
    );
}

fn import(ck: &Path, out: &Path, extra: &[&str]) -> (std::process::Output, String) {
    let mut args = vec![
        OsStr::new("gr00t"),
        OsStr::new("import"),
        ck.as_os_str(),
        OsStr::new("--out"),
        out.as_os_str(),
    ];
    args.extend(extra.iter().map(OsStr::new));
    pir2(&args)
}

/// One NFE of `head` on fixed inputs (πR² per-position timesteps, d_vis = 2).
fn one_nfe(head: &Gr00tN17Head) -> Vec<f32> {
    let dev = Device::Cpu;
    let c = head.config();
    let mut rng = pir2_schedule::Rng::new(5);
    let mut r = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.uniform_range(-1.0, 1.0)).collect() };
    let t = 6;
    let vl = Tensor::from_vec(r(t * D_VL), (1, t, D_VL), &dev).unwrap();
    let vl = head.process_backbone(&vl).unwrap();
    let image = Tensor::new(&[[1u8, 1, 1, 0, 0, 0]], &dev).unwrap();
    let d_vis = Tensor::new(&[2u32], &dev).unwrap();
    let vl = VlTokens {
        embeddings: &vl,
        attention_mask: None,
        image_mask: Some(&image),
        d_vis: Some(&d_vis),
    };
    let emb = Tensor::new(&[10u32], &dev).unwrap();
    let state = Tensor::from_vec(r(c.max_state_dim), (1, 1, c.max_state_dim), &dev).unwrap();
    let s = head.encode_state(&state, &emb).unwrap();
    let x = Tensor::from_vec(r(H * c.max_action_dim), (1, H, c.max_action_dim), &dev).unwrap();
    let ta: Vec<u32> = (0..H as u32).map(|p| 100 * p).collect();
    let tt: Vec<u32> = std::iter::once(999).chain(ta.iter().copied()).collect();
    let ta = Tensor::from_vec(ta, (1, H), &dev).unwrap();
    let tt = Tensor::from_vec(tt, (1, H + 1), &dev).unwrap();
    let ts = Timesteps::PerPosition {
        actions: &ta,
        tokens: &tt,
    };
    head.velocity(&s, &x, ts, &vl, &emb)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

#[test]
fn a_gr00t_checkpoint_imports_and_its_head_runs_as_the_original() {
    let dir = Scratch::new("gr00t-import");
    for sharded in [false, true] {
        let ck = dir.path().join(format!("gr00t-{sharded}"));
        gr00t_checkpoint(&ck, sharded);
        let out = dir.path().join(format!("imported-{sharded}"));
        let (o, text) = import(&ck, &out, &[]);
        eprintln!("{text}");
        assert!(o.status.success(), "import (sharded {sharded}): {text}");
        for f in [
            "config.json",
            "model.safetensors",
            "embodiment.toml",
            "statistics.json",
            "embodiment_id.json",
            "processor_config.json",
            "pir2_gr00t.safetensors",
            "onnx/state_encoder.onnx",
            "onnx/action_encoder.onnx",
            "onnx/dit.onnx",
            "onnx/action_decoder.onnx",
        ] {
            assert!(out.join(f).is_file(), "{f} missing: {text}");
        }
        // What it could not write is named, with how to add it.
        assert!(
            text.contains("tokenizer.json") && text.contains("export_onnx_n1d7.py"),
            "{text}"
        );

        // The embodiment, mapped from GR00T's files.
        let emb = EmbodimentConfig::load(&out.join("embodiment.toml")).unwrap();
        assert_eq!(emb.embodiment_tag, TAG);
        assert_eq!(emb.embodiment_id, 10);
        assert_eq!(emb.horizon, H);
        assert_eq!(emb.n_obs, 1);
        let st: Vec<(&str, usize, Norm)> = emb
            .state
            .iter()
            .map(|g| (g.name.as_str(), g.dim, g.norm))
            .collect();
        assert_eq!(
            st,
            [
                ("arm", 3, Norm::Q01Q99),
                ("wrist", 2, Norm::SinCos),
                ("force", 2, Norm::MeanStd)
            ]
        );
        let arm = &emb.action[0];
        assert!(arm.relative && arm.format == GroupFormat::Default && arm.dim == 3);
        assert_eq!(arm.state_key.as_deref(), Some("arm"));
        assert!(!emb.action[1].relative && emb.action[1].dim == 1);
        assert!(emb.image.letterbox && emb.image.shortest_edge == 256);
        assert!((emb.image.crop_fraction - 0.95).abs() < 1e-12);
        assert_eq!(emb.prompt.chat.images, 1);
        assert_eq!(emb.prompt.image_tokens, 64);
        assert_eq!(emb.policy.trained, pir2_runtime::Policy::Flow);
        assert_eq!(emb.policy.flow_steps, 4);

        // The imported head computes what the GR00T checkpoint's head computes.
        let dev = Device::Cpu;
        let direct = Gr00tN17Head::load(&ck, &dev).unwrap();
        let imported = Gr00tN17Head::load(&out, &dev).unwrap();
        let (a, b) = (one_nfe(&direct), one_nfe(&imported));
        assert_eq!(a, b, "sharded {sharded}");
        assert!(a.iter().all(|v| v.is_finite()));
        // The token table is kept (the split backbone reads it); other backbone tensors not.
        let names = pir2_backends::gr00t::n17::TensorIndex::open(&out, "").unwrap();
        assert!(names.contains(EMBED_TOKENS_KEY));
        assert!(!names.contains("backbone.model.visual.patch_embed.proj.weight"));
        // `pir2 gr00t train` loads it as its base head (zero delay table = the same head).
        let trainable = Gr00tN17Head::load_trainable(&out, emb.d_vis_max, &dev).unwrap();
        assert_eq!(one_nfe(&trainable), a);

        // A non-empty --out is refused.
        let (o, text) = import(&ck, &out, &[]);
        assert!(!o.status.success());
        assert!(
            text.contains("--out") && text.contains("not empty"),
            "{text}"
        );
    }
}

/// `f` breaks one file of a good checkpoint; the import must fail with one error naming
/// `file` and `field`, leaving no output.
fn refused(
    dir: &Path,
    name: &str,
    extra: &[&str],
    f: impl FnOnce(&Path),
    file: &str,
    field: &str,
) -> String {
    let ck = dir.join(format!("bad-{name}"));
    gr00t_checkpoint(&ck, name.contains("shard"));
    f(&ck);
    let out = dir.join(format!("out-{name}"));
    let (o, text) = import(&ck, &out, extra);
    eprintln!("{name}: {text}");
    assert!(!o.status.success(), "{name}: {text}");
    assert!(text.contains(file), "{name}: `{file}` not named: {text}");
    assert!(text.contains(field), "{name}: `{field}` not named: {text}");
    assert_eq!(text.matches("Error").count(), 1, "{name}: {text}");
    assert!(!out.exists(), "{name}: output written");
    text
}

fn edit(path: &Path, f: impl FnOnce(&mut Value)) {
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(path, v.to_string()).unwrap();
}

#[test]
fn bad_or_partial_checkpoints_are_one_error_naming_file_and_field() {
    let dir = Scratch::new("gr00t-import-bad");
    let d = dir.path();
    // A missing file.
    refused(
        d,
        "no-statistics",
        &[],
        |ck| std::fs::remove_file(ck.join("statistics.json")).unwrap(),
        "statistics.json",
        "is missing",
    );
    refused(
        d,
        "no-weights",
        &[],
        |ck| std::fs::remove_file(ck.join("model.safetensors")).unwrap(),
        "model.safetensors",
        "model.safetensors.index.json",
    );
    refused(
        d,
        "shard-missing",
        &[],
        |ck| std::fs::remove_file(ck.join("model-00002-of-00002.safetensors")).unwrap(),
        "model.safetensors.index.json",
        "model-00002-of-00002.safetensors",
    );
    // A missing field.
    refused(
        d,
        "no-delta",
        &[],
        |ck| {
            edit(&ck.join("processor_config.json"), |v| {
                v["processor_kwargs"]["modality_configs"][TAG]["action"]
                    .as_object_mut()
                    .unwrap()
                    .remove("delta_indices");
            })
        },
        "processor_config.json",
        "processor_kwargs.modality_configs.new_embodiment.action.delta_indices",
    );
    refused(
        d,
        "no-q99",
        &[],
        |ck| {
            edit(&ck.join("statistics.json"), |v| {
                v[TAG]["state"]["arm"]
                    .as_object_mut()
                    .unwrap()
                    .remove("q99");
            })
        },
        "statistics.json",
        "q99",
    );
    // A tensor of the wrong shape.
    refused(
        d,
        "bad-shape",
        &[],
        |ck| {
            let cfg = Gr00tN17Config::from_json_file(&ck.join("config.json")).unwrap();
            let mut map: HashMap<String, Tensor> = tensors(&cfg, DType::F32).into_iter().collect();
            let name = format!("{PREFIX}action_decoder.layer2.W");
            map.insert(
                name,
                Tensor::zeros((12, 12, 7), DType::F32, &Device::Cpu).unwrap(),
            );
            candle_core::safetensors::save(&map, ck.join("model.safetensors")).unwrap();
        },
        "model.safetensors",
        "action_head.action_decoder.layer2.W",
    );
    // An unknown embodiment: not in the processor's modality configs, or without a slot.
    refused(
        d,
        "unknown-tag",
        &["--embodiment-tag", "my_robot"],
        |_| {},
        "processor_config.json",
        "modality_configs.my_robot",
    );
    refused(
        d,
        "no-slot",
        &[],
        |ck| {
            edit(&ck.join("embodiment_id.json"), |v| {
                v.as_object_mut().unwrap().remove(TAG);
            })
        },
        "embodiment_id.json",
        TAG,
    );
    // Something pir2 cannot map.
    refused(
        d,
        "delta-actions",
        &[],
        |ck| {
            edit(&ck.join("processor_config.json"), |v| {
                v["processor_kwargs"]["modality_configs"][TAG]["action"]["action_configs"][1]
                    ["rep"] = json!("DELTA");
            })
        },
        "processor_config.json",
        "action.action_configs[1].rep",
    );
    refused(
        d,
        "torchvision",
        &[],
        |ck| {
            edit(&ck.join("processor_config.json"), |v| {
                v["processor_kwargs"]["use_albumentations"] = json!(false);
            })
        },
        "processor_config.json",
        "processor_kwargs.use_albumentations",
    );
    refused(
        d,
        "n16",
        &[],
        |ck| {
            edit(&ck.join("config.json"), |v| {
                v["model_type"] = json!("Gr00tN1d6")
            })
        },
        "config.json",
        "model_type",
    );
}

/// Rows of the synthetic πR² head's delay table (`d_vis_max + 1`).
const DELAY_ROWS: usize = 5;

/// Rewrite the checkpoint's `model.safetensors` as a πR² head fine-tuned in PyTorch would be
/// saved: every AdaLN modulation (`…norm1.linear`, `model.proj_out_1`) as per-position heads
/// `<layer>_heads.{weight [heads, out, in], bias [heads, out]}`, each copy perturbed so the
/// positions differ, except the layer `shared` (kept as GR00T's shared pair), plus a delay
/// table `[DELAY_ROWS, D_in]`.
fn pir2_head(ck: &Path, heads: usize, shared: Option<&str>) {
    let cfg = Gr00tN17Config::from_json_file(&ck.join("config.json")).unwrap();
    let mut map: HashMap<String, Tensor> = tensors(&cfg, DType::F32).into_iter().collect();
    let layers: Vec<String> = map
        .keys()
        .filter_map(|k| k.strip_suffix(".weight"))
        .filter(|k| k.ends_with("norm1.linear") || k.ends_with("model.proj_out_1"))
        .map(str::to_string)
        .collect();
    assert_eq!(layers.len(), 3, "{layers:?}");
    let mut rng = pir2_schedule::Rng::new(41);
    for l in layers {
        if shared.is_some_and(|s| l.ends_with(s)) {
            continue;
        }
        for k in ["weight", "bias"] {
            let t = map.remove(&format!("{l}.{k}")).unwrap();
            let copies: Vec<Tensor> = (0..heads)
                .map(|p| {
                    let noise: Vec<f32> = (0..t.elem_count())
                        .map(|_| rng.uniform_range(-0.05, 0.05))
                        .collect();
                    let noise = Tensor::from_vec(noise, t.shape(), &Device::Cpu).unwrap();
                    ((&t * (1.0 + 0.1 * p as f64)).unwrap() + noise).unwrap()
                })
                .collect();
            map.insert(format!("{l}_heads.{k}"), Tensor::stack(&copies, 0).unwrap());
        }
    }
    let d_in = cfg.input_embedding_dim;
    let delay: Vec<f32> = (0..DELAY_ROWS * d_in)
        .map(|_| rng.uniform_range(-0.5, 0.5))
        .collect();
    map.insert(
        format!("{PREFIX}delay_embedding.weight"),
        Tensor::from_vec(delay, (DELAY_ROWS, d_in), &Device::Cpu).unwrap(),
    );
    candle_core::safetensors::save(&map, ck.join("model.safetensors")).unwrap();
}

#[test]
fn a_pir2_head_fine_tuned_in_pytorch_imports_with_its_heads_and_delay_table() {
    let dir = Scratch::new("gr00t-import-pir2");
    let ck = dir.path().join("gr00t-pir2");
    gr00t_checkpoint(&ck, false);
    pir2_head(&ck, 1 + H, None);
    let out = dir.path().join("imported");
    let (o, text) = import(&ck, &out, &[]);
    eprintln!("{text}");
    assert!(o.status.success(), "import: {text}");
    assert!(
        text.contains("per-position AdaLN heads") && text.contains("trained = \"pi_r2\""),
        "{text}"
    );

    // Declared a πR² head, deployed πR² async, the delay table's rows giving d_vis_max.
    let emb = EmbodimentConfig::load(&out.join("embodiment.toml")).unwrap();
    assert_eq!(emb.policy.trained, pir2_runtime::Policy::PiR2);
    assert_eq!(emb.policy.mode.name(), "pir2_async");
    // The default n = 2, at most what the staircase allows at H = 8, d_max = 3 (n_max = 1).
    assert_eq!(emb.d_max, 3);
    assert_eq!(emb.policy.nfe, 1);
    assert_eq!(emb.d_vis_max, DELAY_ROWS - 1);
    let toml = std::fs::read_to_string(out.join("embodiment.toml")).unwrap();
    assert!(toml.contains("trained = \"pi_r2\""), "{toml}");

    // The imported head is the checkpoint's: heads, delay table, one NFE bit for bit.
    let dev = Device::Cpu;
    let direct = Gr00tN17Head::load(&ck, &dev).unwrap();
    let imported = Gr00tN17Head::load(&out, &dev).unwrap();
    assert_eq!(direct.position_heads(), Some(1 + H));
    assert_eq!(imported.position_heads(), Some(1 + H));
    let (a, b) = (one_nfe(&direct), one_nfe(&imported));
    assert_eq!(a, b);
    assert!(a.iter().all(|v| v.is_finite()));
    // The heads and the delay table matter: the same checkpoint with GR00T's shared layers
    // and no delay table computes another NFE.
    let flat = dir.path().join("flat");
    gr00t_checkpoint(&flat, false);
    let shared = Gr00tN17Head::load(&flat, &dev).unwrap();
    assert_ne!(one_nfe(&shared), a);
    // `pir2 gr00t train` can continue from it (its own delay table, of its size).
    let trainable = Gr00tN17Head::load_trainable(&out, emb.d_vis_max, &dev).unwrap();
    assert_eq!(one_nfe(&trainable), a);

    // The side file of the ONNX head carries the delay table as trained.
    let side = candle_core::safetensors::load(out.join("pir2_gr00t.safetensors"), &dev).unwrap();
    let table = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(
        table(&side["delay_embedding.weight"]),
        table(direct.delay_embedding().unwrap())
    );
    // The DiT graph carries the per-position heads (one initializer per layer).
    let dit = std::fs::read(out.join("onnx/dit.onnx")).unwrap();
    let has = |s: &str| dit.windows(s.len()).any(|w| w == s.as_bytes());
    assert!(has("proj_out_1_heads.weight"), "no heads in dit.onnx");
    // And the ONNX head `pir2 gr00t run` uses computes what the candle head computes on
    // what the graphs were fed (recorded with `record_nfe`).
    onnx_call_matches_candle(&out, &direct, &dir.path().join("rec"));
}

/// One call of the imported ONNX head (`Gr00tActionHead`, πR² per-position τ, `d_vis` = 2),
/// recorded; then the candle head `candle` on the recorded graph inputs gives the recorded
/// DiT tokens and velocity.
fn onnx_call_matches_candle(out: &Path, candle: &Gr00tN17Head, rec: &Path) {
    use pir2_backends::gr00t::{CheckpointFiles, Gr00tActionHead, Normalizer, VlLayout};
    use pir2_runtime::{ModelInput, SlowInput};
    let files = CheckpointFiles::in_dir(out);
    let cfg = EmbodimentConfig::load(&out.join("embodiment.toml")).unwrap();
    let norm = Normalizer::load(&files.statistics, &cfg).unwrap();
    let ort = pir2_backends::ort::OrtOptions::default();
    let mut head = Gr00tActionHead::load(&files, &cfg, norm, cfg.embodiment_id, &ort).unwrap();
    let t = 6;
    head.set_vl_layout(VlLayout {
        image_mask: (0..t).map(|i| i < 3).collect(),
        attention_mask: vec![true; t],
    });
    head.record_nfe(rec, 1).unwrap();
    let (h, a, sd) = (cfg.horizon, cfg.action_dim(), cfg.state_dim());
    let mut rng = pir2_schedule::Rng::new(9);
    let mut r = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.uniform_range(-1.0, 1.0)).collect() };
    let (x, obs, vl) = (r(h * a), r(sd), r(t * D_VL));
    let tau: Vec<f32> = (0..h).map(|p| 0.1 + 0.8 * p as f32 / h as f32).collect();
    let input = ModelInput {
        batch: 1,
        horizon: h,
        action_dim: a,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: 1,
        fast_dim: sd,
        slow: SlowInput::Tokens {
            data: &vl,
            tokens: t,
            dim: D_VL,
        },
        d_vis: &[2],
    };
    let mut v = vec![0.0; h * a];
    head.forward(&input, &mut v).unwrap();

    let dev = Device::Cpu;
    let rt = candle_core::safetensors::load(rec.join("nfe-0000.safetensors"), &dev).unwrap();
    let flat = |t: &Tensor| -> Vec<f32> {
        t.to_dtype(DType::F32)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    };
    let close = |what: &str, got: &[f32], want: &[f32]| {
        assert_eq!(got.len(), want.len(), "{what}");
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g - w).abs() <= 1e-4 * (1.0 + w.abs()),
                "{what}[{i}]: ONNX {g}, candle {w}"
            );
        }
    };
    assert_eq!(flat(&rt["velocity"]), v);
    let (sa, want) = candle_on_recorded_call(candle, &rt, 1, a);
    close("sa_embs", &flat(&rt["sa_embs"]), &flat(&sa));
    close("velocity", &v, &flat(&want));
}

#[test]
fn pir2_heads_of_the_wrong_count_mixed_or_declared_a_baseline_are_refused() {
    let dir = Scratch::new("gr00t-import-pir2-bad");
    let d = dir.path();
    // H heads where 1 + H are needed: the tensor, the file and both counts.
    let text = refused(
        d,
        "heads-count",
        &[],
        |ck| pir2_head(ck, H, None),
        "model.safetensors",
        "action_head.model.transformer_blocks.0.norm1.linear_heads.weight",
    );
    assert!(
        text.contains(&format!("has {H} per-position heads"))
            && text.contains(&format!("1 + H = {}", H + 1)),
        "{text}"
    );
    // One layer shared, the others per-position.
    refused(
        d,
        "heads-mixed",
        &[],
        |ck| pir2_head(ck, 1 + H, Some("model.proj_out_1")),
        "model.safetensors",
        "action_head.model.proj_out_1.weight",
    );
    // A πR² head declared a baseline, or an n that does not fit the staircase.
    for (name, extra) in [
        ("heads-as-flow", ["--trained", "flow"]),
        ("heads-as-rtc", ["--trained", "rtc"]),
    ] {
        let text = refused(
            d,
            name,
            &extra,
            |ck| pir2_head(ck, 1 + H, None),
            "model.safetensors",
            "--trained",
        );
        assert!(text.contains("per-position"), "{text}");
    }
    refused(
        d,
        "nfe-too-big",
        &["--nfe", "2"],
        |ck| pir2_head(ck, 1 + H, None),
        "model.safetensors",
        "--nfe",
    );
    refused(
        d,
        "nfe-for-flow",
        &["--nfe", "2"],
        |_| {},
        "model.safetensors",
        "--nfe",
    );
}
