//! Issue 46's user path, through the binary only: a released-layout GR00T N1.7 checkpoint →
//! `pir2 gr00t import --backbone-onnx EXPORT` → the tokenizer copied in → `pir2 gr00t
//! features` over a LeRobot v3.0 video dataset → `pir2 gr00t train` (2 steps) → `pir2 gr00t
//! export` → the backbone and tokenizer copied in → `pir2 gr00t run gr00t-xarm-xhand --emulate`.
//! Every step must succeed and leave its output; a step whose input is missing (the
//! tokenizer before `features`, the backbone before `run`) must fail naming it.
//!
//! What is synthetic (tiny sizes, random weights, nothing of NVIDIA's):
//! - the GR00T checkpoint: every file of the released set (`config.json`,
//!   `model-0000K-of-00002.safetensors` in bfloat16 + `model.safetensors.index.json`,
//!   `processor_config.json`, `statistics.json`, `embodiment_id.json`) in Isaac-GR00T's schema
//!   (see `gr00t_import.rs` for the sources), with random action-head weights and a random
//!   token table. Its embodiment is the one `gr00t-xarm-xhand` drives (the emulators take
//!   the xArm6 + XHand action layout, by name, width and order): state `arm_joints` 6,
//!   `hand_joints` 12, `hand_torques` 12, `fingertip_forces` 15; action `arm_joints` 6
//!   (relative to the state's) + `hand_joints` 12; two cameras `front` and `wrist`;
//! - NVIDIA's ONNX export (`EXPORT`): the split-backbone stand-ins of
//!   `pir2_backends::gr00t::testing::write_split_backbone` (ViT in float32, LLM in bfloat16 as
//!   the exporter writes it by default, so the import's rewrite to float32 runs), not GR00T's
//!   graphs;
//! - the tokenizer: the small Qwen3-VL-shaped BPE `tokenizer.json` of the testing module, in
//!   place of Cosmos-Reason2-2B's (the README: copied into the imported directory);
//! - the dataset: a copy of the video fixture `pir2-sim/tests/fixtures/lerobot_video` (its
//!   real AV1 and H.264 videos, 2 episodes of 5 and 7 frames, 10 fps) whose `observation.state`
//!   and `action` columns are replaced with 45 and 18 values per frame (smooth synthetic
//!   trajectories), so that they fit the embodiment.
//!
//! Two edits a user makes by hand are made here the same way, on the imported
//! `embodiment.toml` written to a separate file: `cameras` (the import leaves it empty, see
//! docs/gr00t-import.md) and `[policy]` (the import declares a released flow head; it is
//! fine-tuned as πR² and run as πR² async). Needs `source .native/env.sh` (ONNX Runtime,
//! `ffmpeg`, `$PIR2_PYTHON` with `onnx` and `pyarrow`).
#![cfg(feature = "gr00t")]

use std::collections::HashMap;
use std::ffi::OsString;
use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use pir2_backends::gr00t::n17::{head_tensor_shapes, Gr00tN17Config, PREFIX};
use pir2_backends::gr00t::testing::{
    python_from_env, write_split_backbone, BPE_TOKENIZER_CONFIG, BPE_TOKENIZER_JSON, D_VL,
    SPLIT_VOCAB,
};
use pir2_backends::gr00t::{DeployKind, EmbodimentConfig, ImagePipeline, EMBED_TOKENS_KEY};
use serde_json::{json, Value};

mod common;
use common::gr00t::{copy_dir, video_fixture as fixture};
use common::gr00t::{pir2_text, read_json, run_python, train_args};
use common::Scratch;

const TAG: &str = "new_embodiment";
/// The projector slot `_PROJECTOR_INDEX_GROUPS` gives `new_embodiment`.
const SLOT: usize = 10;
/// Chunk length: both fixture episodes (5 and 7 frames) hold whole chunks.
const H: usize = 5;
/// Shortest image edge: one merged 32-px patch grid per view, 1 image token.
const EDGE: usize = 32;
const VIDEO: [&str; 2] = ["front", "wrist"];
const STATE: [(&str, usize); 4] = [
    ("arm_joints", 6),
    ("hand_joints", 12),
    ("hand_torques", 12),
    ("fingertip_forces", 15),
];
const ACTION: [(&str, usize); 2] = [("arm_joints", 6), ("hand_joints", 12)];
/// The dataset's frame rate (the import's `--control-hz`).
const FPS: &str = "10";
const TICKS: u64 = 20;

fn write_json(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(v).unwrap()).unwrap();
}

/// `Gr00tN1d7Config` at tiny widths: `D_vl` of the split stand-ins, room for 45 state and
/// 18 action values, 12 embodiment slots, 2 DiT blocks.
fn config_json() -> Value {
    json!({
        "model_type": "Gr00tN1d7",
        "model_dtype": "bfloat16",
        "model_name": "nvidia/Cosmos-Reason2-2B",
        "backbone_model_type": "qwen",
        "select_layer": 12,
        "action_horizon": 8,
        "add_pos_embed": true,
        "attend_text_every_n_blocks": 2,
        "backbone_embedding_dim": D_VL,
        "diffusion_model_cfg": {
            "positional_embeddings": null,
            "num_layers": 2,
            "num_attention_heads": 2,
            "attention_head_dim": 8,
            "norm_type": "ada_norm",
            "dropout": 0.2,
            "final_dropout": true,
            "output_dim": 16,
            "interleave_self_attention": true
        },
        "hidden_size": 16,
        "input_embedding_dim": 16,
        "max_action_dim": 20,
        "max_num_embodiments": 12,
        "max_seq_len": 16,
        "max_state_dim": 48,
        "num_inference_timesteps": 4,
        "num_timestep_buckets": 1000,
        "state_history_length": 1,
        "use_alternate_vl_dit": true,
        "use_vlln": true,
        "use_percentiles": true,
        "use_relative_action": true
    })
}

fn keys(groups: &[(&str, usize)]) -> Vec<String> {
    groups.iter().map(|(k, _)| k.to_string()).collect()
}

/// `Gr00tN1d7Processor.save_pretrained`'s file for the embodiment above.
fn processor_json() -> Value {
    let none = Value::Null;
    let modality = json!({
        "video": {"delta_indices": [0], "modality_keys": VIDEO,
                  "sin_cos_embedding_keys": none, "mean_std_embedding_keys": none,
                  "action_configs": none},
        "state": {"delta_indices": [0], "modality_keys": keys(&STATE),
                  "sin_cos_embedding_keys": none,
                  "mean_std_embedding_keys": ["hand_torques", "fingertip_forces"],
                  "action_configs": none},
        "action": {"delta_indices": (0..H).collect::<Vec<_>>(), "modality_keys": keys(&ACTION),
                   "sin_cos_embedding_keys": none, "mean_std_embedding_keys": none,
                   "action_configs": [
                       {"rep": "RELATIVE", "type": "NON_EEF", "format": "DEFAULT", "state_key": "arm_joints"},
                       {"rep": "ABSOLUTE", "type": "NON_EEF", "format": "DEFAULT", "state_key": none}
                   ]},
        "language": {"delta_indices": [0], "modality_keys": ["annotation.human.task_description"],
                     "sin_cos_embedding_keys": none, "mean_std_embedding_keys": none,
                     "action_configs": none}
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
            "shortest_image_edge": EDGE,
            "crop_fraction": 0.95,
            "letter_box_transform": true,
            "model_name": "nvidia/Cosmos-Reason2-2B",
            "model_type": "qwen",
            "formalize_language": true,
            "max_state_dim": 48,
            "max_action_dim": 20,
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

/// Statistics of one group: every statistic over `[lo, hi]`, a vector or (`rows`) a table.
fn stats(dim: usize, rows: Option<usize>, lo: f64, hi: f64) -> Value {
    let v = |x: f64| match rows {
        None => json!(vec![x; dim]),
        Some(r) => json!(vec![vec![x; dim]; r]),
    };
    let (mid, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
    json!({"min": v(lo), "max": v(hi), "mean": v(mid), "std": v(half / 2.0),
           "q01": v(lo + 0.01 * half), "q99": v(hi - 0.01 * half)})
}

/// The ranges of the synthetic trajectories of [`DATASET_PY`].
fn range(modality: &str, group: &str) -> (f64, f64) {
    match (modality, group) {
        (_, "arm_joints") => (-0.1, 0.1),
        (_, "hand_joints") => (0.2, 0.6),
        (_, "hand_torques") => (-50.0, 50.0),
        _ => (-5.0, 5.0),
    }
}

fn statistics_json() -> Value {
    let table = |modality: &str, groups: &[(&str, usize)]| -> Value {
        let m: serde_json::Map<String, Value> = groups
            .iter()
            .map(|&(g, d)| {
                let (lo, hi) = range(modality, g);
                (g.to_string(), stats(d, None, lo, hi))
            })
            .collect();
        Value::Object(m)
    };
    json!({TAG: {
        "state": table("state", &STATE),
        "action": table("action", &ACTION),
        "relative_action": {"arm_joints": stats(6, Some(H), -0.2, 0.2)}
    }})
}

/// The released file set in `dir`: the action head's tensors (random) and the VLM's token
/// table (random, `[SPLIT_VOCAB, D_vl]`) in bfloat16, in two shards with their index.
fn gr00t_checkpoint(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    write_json(&dir.join("config.json"), &config_json());
    write_json(&dir.join("processor_config.json"), &processor_json());
    write_json(&dir.join("statistics.json"), &statistics_json());
    write_json(
        &dir.join("embodiment_id.json"),
        &json!({"oxe_droid": 0, "libero_sim": 2, TAG: SLOT}),
    );
    let cfg = Gr00tN17Config::from_json_file(&dir.join("config.json")).unwrap();
    let mut rng = pir2_schedule::Rng::new(46);
    let mut shapes: Vec<(String, Vec<usize>)> = head_tensor_shapes(&cfg)
        .into_iter()
        .map(|(n, s)| (format!("{PREFIX}{n}"), s))
        .collect();
    shapes.push((EMBED_TOKENS_KEY.to_string(), vec![SPLIT_VOCAB, D_VL]));
    let mut all = Vec::new();
    for (name, shape) in shapes {
        let n: usize = shape.iter().product();
        let fan_in = if shape.len() >= 2 {
            shape[shape.len() - 2]
        } else {
            1
        };
        let s = 1.0 / (fan_in as f32).sqrt();
        let v: Vec<f32> = (0..n)
            .map(|_| {
                let u = rng.uniform_range(-s, s);
                if name.ends_with("vlln.weight") {
                    1.0 + u
                } else {
                    u
                }
            })
            .collect();
        let t = Tensor::from_vec(v, shape, &Device::Cpu)
            .unwrap()
            .to_dtype(DType::BF16)
            .unwrap();
        all.push((name, t));
    }
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
    write_json(
        &dir.join("model.safetensors.index.json"),
        &json!({"metadata": {"total_size": 0}, "weight_map": weight_map}),
    );
}

/// The embodiment the import makes of [`processor_json`] as far as the backbone sees it
/// (GR00T N1.7's image pipeline at [`EDGE`] px, two views, Cosmos-Reason2-2B's patching).
fn backbone_embodiment() -> EmbodimentConfig {
    let mut e = EmbodimentConfig::xarm6_xhand();
    e.image.pipeline = ImagePipeline::Gr00tN17;
    e.image.letterbox = true;
    e.image.shortest_edge = EDGE;
    e.image.crop_fraction = 0.95;
    let per_side = EDGE / (e.vision.patch_size * e.vision.merge_size);
    e.prompt.chat.images = VIDEO.len();
    e.prompt.image_tokens = VIDEO.len() * per_side * per_side;
    e
}

/// NVIDIA's exporter output stand-in in `export`: `vit_fp32.onnx` and `llm_bf16.onnx` made
/// in the scratch directory `work` for [`backbone_embodiment`] with the BPE tokenizer.
fn exporter_output(work: &Path, export: &Path, python: &Path) {
    std::fs::create_dir_all(work.join("onnx")).unwrap();
    let emb = backbone_embodiment();
    std::fs::write(work.join("embodiment.toml"), emb.to_toml().unwrap()).unwrap();
    std::fs::write(work.join("tokenizer.json"), BPE_TOKENIZER_JSON).unwrap();
    std::fs::write(work.join("tokenizer_config.json"), BPE_TOKENIZER_CONFIG).unwrap();
    write_split_backbone(work, "pick the cube", "llm_bf16", python).unwrap();
    std::fs::create_dir_all(export).unwrap();
    for f in ["vit_fp32.onnx", "llm_bf16.onnx"] {
        std::fs::copy(work.join("onnx").join(f), export.join(f)).unwrap();
    }
}

/// Replaces the fixture copy's `observation.state` (4) and `action` (4) columns with the
/// embodiment's 45 state and 18 action values per frame (the groups' ranges of
/// [`range`]), and their entries in `meta/info.json`.
const DATASET_PY: &str = r#"
import json, sys
import numpy as np
import pyarrow as pa, pyarrow.parquet as pq
root = sys.argv[1]
path = f"{root}/data/chunk-000/file-000.parquet"
t = pq.read_table(path)
eps, frames = t["episode_index"].to_pylist(), t["frame_index"].to_pylist()
def wave(ph, n, k):
    return np.sin(ph + 0.7 * np.arange(n) + k)
state, action = [], []
for ep, fr in zip(eps, frames):
    ph = 0.3 * fr + ep
    state.append(np.concatenate([0.09 * wave(ph, 6, 0), 0.4 + 0.19 * wave(ph, 12, 1),
                                 45.0 * wave(ph, 12, 2), 4.5 * wave(ph, 15, 3)]))
    action.append(np.concatenate([0.09 * wave(ph + 0.3, 6, 0), 0.4 + 0.19 * wave(ph + 0.3, 12, 1)]))
def column(rows, n):
    flat = pa.array(np.asarray(rows, np.float32).reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, n)
t = t.set_column(t.schema.get_field_index("observation.state"), "observation.state", column(state, 45))
t = t.set_column(t.schema.get_field_index("action"), "action", column(action, 18))
pq.write_table(t, path)
info_path = f"{root}/meta/info.json"
info = json.load(open(info_path))
info["features"]["observation.state"] = {"dtype": "float32", "shape": [45], "names": [f"q{i}" for i in range(45)]}
info["features"]["action"] = {"dtype": "float32", "shape": [18], "names": [f"a{i}" for i in range(18)]}
json.dump(info, open(info_path, "w"), indent=4)
"#;

/// Runs `pir2 ARGS` as step `what`: it must succeed and leave every file of `outputs`.
fn step<S: AsRef<std::ffi::OsStr>>(what: &str, args: &[S], outputs: &[&Path]) -> String {
    let t0 = Instant::now();
    let (o, text) = pir2_text(args);
    eprintln!("--- {what} ({:.1} s)\n{text}", t0.elapsed().as_secs_f64());
    assert!(o.status.success(), "{what} failed: {text}");
    for p in outputs {
        assert!(
            p.exists(),
            "{what} succeeded but left no {}: {text}",
            p.display()
        );
    }
    text
}

/// Runs `pir2 ARGS` as step `what` with an input missing: it must fail, naming `named`.
fn refused<S: AsRef<std::ffi::OsStr>>(what: &str, args: &[S], named: &str) {
    let (o, text) = pir2_text(args);
    eprintln!("--- {what} (must fail)\n{text}");
    assert!(!o.status.success(), "{what} succeeded: {text}");
    assert!(text.contains(named), "{what}: `{named}` not named: {text}");
}

fn os(v: &[&dyn AsRef<std::ffi::OsStr>]) -> Vec<OsString> {
    v.iter().map(|s| s.as_ref().to_os_string()).collect()
}

#[test]
fn a_released_layout_checkpoint_imports_trains_exports_and_runs() {
    let t0 = Instant::now();
    let dir = Scratch::new("gr00t-user-path");
    let root = dir.path();
    let python = python_from_env().unwrap();
    let (ck, export, imported, data) = (
        root.join("GR00T-N1.7-synthetic"),
        root.join("onnx-export"),
        root.join("imported"),
        root.join("data"),
    );
    gr00t_checkpoint(&ck);
    exporter_output(&root.join("exporter-work"), &export, &python);
    copy_dir(&fixture(), &data);
    run_python(
        &python,
        &root.join("dataset.py"),
        DATASET_PY,
        &[data.as_os_str()],
        "45/18-wide dataset",
    );

    // 1. Import, with the exporter's ViT and (bfloat16) LLM graphs.
    let text = step(
        "import",
        &os(&[
            &"gr00t",
            &"import",
            &ck,
            &"--out",
            &imported,
            &"--backbone-onnx",
            &export,
            &"--control-hz",
            &FPS,
        ]),
        &[
            &imported.join("onnx/vit_fp32.onnx"),
            &imported.join("onnx/llm_fp32.onnx"),
            &imported.join("onnx/dit.onnx"),
            &imported.join("model.safetensors"),
            &imported.join("embodiment.toml"),
        ],
    );
    assert!(
        text.contains("onnx/llm_fp32.onnx: bfloat16 → float32"),
        "the bfloat16 LLM was not rewritten: {text}"
    );
    assert!(!imported.join("onnx/llm_bf16.onnx").exists());
    // The import names the tokenizer as the one thing left to add.
    assert!(
        text.contains("tokenizer.json") && !text.contains("vit_fp32.onnx, onnx/llm_fp32.onnx:"),
        "{text}"
    );
    let mut emb = EmbodimentConfig::load(&imported.join("embodiment.toml")).unwrap();
    let widths = |g: &[pir2_backends::gr00t::Group]| -> Vec<(String, usize)> {
        g.iter().map(|g| (g.name.clone(), g.dim)).collect()
    };
    let named = |g: &[(&str, usize)]| -> Vec<(String, usize)> {
        g.iter().map(|&(n, d)| (n.to_string(), d)).collect()
    };
    assert_eq!(widths(&emb.state), named(&STATE));
    assert_eq!(widths(&emb.action), named(&ACTION));
    assert!(emb.action[0].relative && !emb.action[1].relative);
    assert_eq!((emb.horizon, emb.embodiment_id), (H, SLOT as i64));
    // The stand-ins were made for the backbone the import describes.
    let bb = backbone_embodiment();
    assert_eq!(
        (&emb.image, &emb.prompt.image_tokens),
        (&bb.image, &bb.prompt.image_tokens)
    );
    assert_eq!(emb.prompt.chat.images, bb.prompt.chat.images);

    // The user's edits, in a file of their own: the dataset's cameras, and πR².
    emb.cameras = VIDEO
        .iter()
        .map(|v| format!("observation.images.{v}"))
        .collect();
    emb.policy.trained = pir2_runtime::Policy::PiR2;
    emb.policy.mode = DeployKind::PiR2Async;
    // πR²'s fresh alignment needs H ≥ 3·d − 1: the import gives this H = 5 the d_max = 2 it
    // takes (not the default 5, nor H − 1 = 4, which the trainer would refuse).
    assert_eq!(emb.d_max, 2);
    let emb_path = root.join("embodiment.toml");
    std::fs::write(&emb_path, emb.to_toml().unwrap()).unwrap();

    // 2. Features: refused without the tokenizer, then with it copied in as the README says.
    let feats = root.join("features.safetensors");
    let features_args = os(&[
        &"gr00t",
        &"features",
        &"--checkpoint",
        &imported,
        &"--data",
        &data,
        &"--embodiment",
        &emb_path,
        &"--out",
        &feats,
    ]);
    refused(
        "features without tokenizer.json",
        &features_args,
        "tokenizer.json",
    );
    assert!(!feats.exists());
    std::fs::write(imported.join("tokenizer.json"), BPE_TOKENIZER_JSON).unwrap();
    std::fs::write(imported.join("tokenizer_config.json"), BPE_TOKENIZER_CONFIG).unwrap();
    let text = step("features", &features_args, &[&feats]);
    assert!(
        text.contains("split export") && text.contains("[12, "),
        "{text}"
    );

    // 3. Train two steps.
    let run = root.join("run");
    let mut args = train_args(&imported, &data, &emb_path, &feats, &run);
    args.extend(
        [
            "--steps",
            "2",
            "--batch-size",
            "4",
            "--checkpoint-every",
            "2",
            "--seed",
            "1",
        ]
        .map(OsString::from),
    );
    let stepdir = run.join("step-000002");
    step("train", &args, &[&stepdir.join("model.safetensors")]);

    // 4. Export the fine-tuned head.
    let out = root.join("deploy");
    let text = step(
        "export",
        &os(&[&"gr00t", &"export", &stepdir, &"--out", &out]),
        &[
            &out.join("onnx/dit.onnx"),
            &out.join("pir2_gr00t.safetensors"),
            &out.join("embodiment.toml"),
        ],
    );
    assert!(text.contains("trained as pi_r2"), "{text}");

    // 5. Run: refused without the backbone, then with the imported backbone, token table and
    //    tokenizer copied in.
    let json_path = root.join("run.json");
    let run_args = os(&[
        &"gr00t",
        &"run",
        &"gr00t-xarm-xhand",
        &"--checkpoint",
        &out,
        &"--task",
        &"pick the cube",
        &"--emulate",
        &"--ticks",
        &TICKS.to_string(),
        &"--json",
        &json_path,
    ]);
    std::fs::write(out.join("tokenizer.json"), BPE_TOKENIZER_JSON).unwrap();
    refused("run without the backbone", &run_args, "backbone");
    let _ = std::fs::remove_file(&json_path);
    for f in [
        "onnx/vit_fp32.onnx",
        "onnx/llm_fp32.onnx",
        "model.safetensors",
        "tokenizer_config.json",
    ] {
        std::fs::copy(imported.join(f), out.join(f)).unwrap();
    }
    step("run", &run_args, &[&json_path]);
    let v = read_json(&json_path);
    assert_eq!(v["mode"]["kind"], "pi_r2_async", "{v}");
    assert_eq!(v["trace"]["ticks"], TICKS, "{v}");
    assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1, "{v}");
    assert!(v["head"].as_str().unwrap().contains("ONNX"), "{v}");
    eprintln!("user path: {:.1} s", t0.elapsed().as_secs_f64());
}
