//! Issue 20's chain through the binary, tiny: a synthetic N1.7-shaped checkpoint (GR00T's
//! tensor names, random weights, sized for the xArm6 + XHand embodiment and the synthetic
//! backbone of `pir2_backends::gr00t::testing`) → `pir2 gr00t train` (2 steps) → `pir2
//! gr00t export` → `pir2 gr00t run gr00t-xarm-xhand --emulate` (25 ticks); and the export's
//! input errors. Needs `source .native/env.sh` (ONNX Runtime for the run, `$PIR2_PYTHON`
//! with `onnx` for the synthetic backbone graph).
#![cfg(feature = "gr00t")]

use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::process::Output;

use candle_core::{Device, Tensor};
use pir2_backends::gr00t::n17::{head_tensor_shapes, Gr00tN17Config, PREFIX};
use pir2_backends::gr00t::testing::{
    python_from_env, tiny_embodiment, write_tiny_checkpoint, D_VL, TOKENS,
};
use pir2_backends::gr00t::EmbodimentConfig;
use pir2_sim::dataset::{DatasetSpec, DatasetWriter, Episode, FeatureKeys, WriteMode};

mod common;
use common::gr00t::{pir2_text as pir2, read_json, train_args};
use common::Scratch;

const H: usize = 16;
const SLOT: i64 = 3;
const EPISODES: usize = 2;
/// At least `H`: the trainer draws only chunks inside an episode, as GR00T does.
const FRAMES: usize = 18;

/// The synthetic N1.7 configuration: `D_vl` of the synthetic backbone, room for the 45
/// state and 18 action values, 2 DiT blocks (one cross-attending, one self-attending).
fn config_json() -> serde_json::Value {
    serde_json::json!({
        "model_type": "Gr00tN1d7",
        "action_horizon": H,
        "add_pos_embed": true,
        "attend_text_every_n_blocks": 2,
        "backbone_embedding_dim": D_VL,
        "diffusion_model_cfg": {
            "positional_embeddings": null,
            "num_layers": 2,
            "num_attention_heads": 2,
            "attention_head_dim": 8,
            "norm_type": "ada_norm",
            "output_dim": 16,
            "interleave_self_attention": true
        },
        "hidden_size": 16,
        "input_embedding_dim": 16,
        "max_action_dim": 20,
        "max_num_embodiments": 4,
        "max_seq_len": H,
        "max_state_dim": 48,
        "num_inference_timesteps": 4,
        "state_history_length": 1,
        "use_alternate_vl_dit": true,
        "use_vlln": true,
        "vl_self_attention_cfg": null
    })
}

fn synthetic_checkpoint(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let cfg_path = dir.join("config.json");
    std::fs::write(&cfg_path, config_json().to_string()).unwrap();
    let cfg = Gr00tN17Config::from_json_file(&cfg_path).unwrap();
    let mut rng = pir2_schedule::Rng::new(17);
    let mut map = std::collections::HashMap::new();
    for (name, shape) in head_tensor_shapes(&cfg) {
        let n: usize = shape.iter().product();
        let fan_in = if shape.len() >= 2 {
            shape[shape.len() - 2]
        } else {
            1
        };
        let s = if name.ends_with("norm1.weight") || name == "vlln.weight" {
            0.0
        } else {
            1.0 / (fan_in as f32).sqrt()
        };
        let v: Vec<f32> = (0..n)
            .map(|_| {
                let u = rng.uniform_range(-s, s);
                if name == "vlln.weight" {
                    1.0 + u
                } else {
                    u
                }
            })
            .collect();
        let t = Tensor::from_vec(v, shape, &Device::Cpu).unwrap();
        map.insert(format!("{PREFIX}{name}"), t);
    }
    candle_core::safetensors::save(&map, dir.join("model.safetensors")).unwrap();
}

/// The synthetic backbone's embodiment (16 px image, 4 image + 4 text tokens) with H = 16,
/// slot 3, d_vis_max 5, trained as πR² (the `[policy]` default).
fn embodiment() -> EmbodimentConfig {
    let mut e = tiny_embodiment();
    e.horizon = H;
    e.embodiment_id = SLOT;
    e.validate().unwrap();
    e
}

/// Episodes of 45 state and 18 action values (arm near 0, hand in 0.2..0.6).
fn dataset(root: &Path, emb: &EmbodimentConfig) {
    let (sd, ad) = (emb.state_dim(), emb.action_dim());
    let names = |p: &str, n: usize| (0..n).map(|i| format!("{p}{i}")).collect::<Vec<_>>();
    let spec = DatasetSpec {
        fps: 25,
        robot_type: Some("xarm6_xhand".into()),
        tasks: vec!["catch the book".into()],
        fast_names: names("q", sd),
        slow_names: Vec::new(),
        action_names: names("a", ad),
        keys: FeatureKeys::default(),
    };
    let mut w = DatasetWriter::open(root, spec, WriteMode::New).unwrap();
    for e in 0..EPISODES {
        let mut ep = Episode::new(sd, 0, ad);
        for t in 0..FRAMES {
            let ph = 0.3 * t as f32 + e as f32;
            let q: Vec<f32> = (0..sd).map(|i| (ph + i as f32).sin()).collect();
            let a: Vec<f32> = (0..ad)
                .map(|i| {
                    let s = (ph + 0.2 + i as f32).sin();
                    if i < 6 {
                        0.1 * s
                    } else {
                        0.4 + 0.2 * s
                    }
                })
                .collect();
            ep.push(&q, &[], &a);
        }
        w.append(&ep).unwrap();
    }
    w.finish().unwrap();
}

/// Backbone outputs for every frame in the synthetic backbone's layout: 4 image tokens,
/// then 4 text tokens.
fn features(path: &Path, frames: usize) {
    let dev = Device::Cpu;
    let emb = common::gr00t::seeded_normal((frames, TOKENS, D_VL), 0x6e02);
    let image: Vec<u8> = (0..frames)
        .flat_map(|_| (0..TOKENS).map(|k| (k < 4) as u8))
        .collect();
    let map = std::collections::HashMap::from([
        ("embeddings".to_string(), emb),
        (
            "image_mask".to_string(),
            Tensor::from_vec(image, (frames, TOKENS), &dev).unwrap(),
        ),
    ]);
    candle_core::safetensors::save(&map, path).unwrap();
}

fn export(step: &Path, out: &Path) -> (Output, String) {
    pir2(&[
        OsStr::new("gr00t"),
        OsStr::new("export"),
        step.as_os_str(),
        OsStr::new("--out"),
        out.as_os_str(),
    ])
}

/// A trained run in a scratch directory named after `tag`: `(scratch, run dir)`.
fn trained(tag: &str) -> (Scratch, PathBuf) {
    let dir = Scratch::new(tag);
    let root = dir.path().to_path_buf();
    let (ck, data, emb_path, feats, run) = (
        root.join("n17"),
        root.join("data"),
        root.join("embodiment.toml"),
        root.join("features.safetensors"),
        root.join("run"),
    );
    synthetic_checkpoint(&ck);
    let emb = embodiment();
    std::fs::write(&emb_path, emb.to_toml().unwrap()).unwrap();
    dataset(&data, &emb);
    features(&feats, EPISODES * FRAMES);
    let mut args = train_args(&ck, &data, &emb_path, &feats, &run);
    args.extend(
        [
            "--steps",
            "2",
            "--batch-size",
            "4",
            "--checkpoint-every",
            "2",
            "--seed",
            "3",
        ]
        .map(OsString::from),
    );
    let (out, text) = pir2(&args);
    assert!(out.status.success(), "train: {text}");
    (dir, run)
}

/// `pir2 gr00t run gr00t-xarm-xhand` of the export `ck` (with the head of `candle_head` in candle,
/// if given) on the emulators for 25 ticks, its report written to `json`.
fn run_emulated(ck: &Path, candle_head: Option<&Path>, json: &Path) -> (Output, String) {
    let mut args = vec![
        OsStr::new("gr00t"),
        OsStr::new("run"),
        OsStr::new("gr00t-xarm-xhand"),
        OsStr::new("--checkpoint"),
        ck.as_os_str(),
    ];
    if let Some(step) = candle_head {
        args.extend([OsStr::new("--candle-head"), step.as_os_str()]);
    }
    args.extend([
        OsStr::new("--task"),
        OsStr::new("catch_book"),
        OsStr::new("--emulate"),
        OsStr::new("--ticks"),
        OsStr::new("25"),
        OsStr::new("--json"),
        json.as_os_str(),
    ]);
    pir2(&args)
}

#[test]
fn trained_head_exports_and_runs_on_the_emulators() {
    let (dir, run) = trained("gr00t-export-run");
    let step = run.join("step-000002");
    let ck = dir.path().join("export");
    let (out, text) = export(&step, &ck);
    assert!(out.status.success(), "export: {text}");
    eprintln!("{text}");
    for f in [
        "onnx/state_encoder.onnx",
        "onnx/action_encoder.onnx",
        "onnx/dit.onnx",
        "onnx/action_decoder.onnx",
        "pir2_gr00t.safetensors",
        "statistics.json",
        "embodiment.toml",
    ] {
        assert!(ck.join(f).is_file(), "{f} missing: {text}");
    }
    // N1.7 has no VL self-attention: no graph for it.
    assert!(!ck.join("onnx/vl_self_attention.onnx").exists());
    let toml = std::fs::read_to_string(ck.join("embodiment.toml")).unwrap();
    assert!(
        toml.contains("[policy]") && toml.contains("trained = \"pi_r2\""),
        "{toml}"
    );

    // The backbone is not part of the export: the synthetic one, dimension-matched.
    let bb = dir.path().join("backbone");
    write_tiny_checkpoint(&bb, "", &python_from_env().unwrap()).unwrap();
    std::fs::copy(bb.join("onnx/backbone.onnx"), ck.join("onnx/backbone.onnx")).unwrap();
    std::fs::copy(bb.join("vocab.txt"), ck.join("vocab.txt")).unwrap();

    let json = dir.path().join("run.json");
    let (out, text) = run_emulated(&ck, None, &json);
    assert!(out.status.success(), "run: {text}");
    let v = read_json(&json);
    assert_eq!(v["mode"]["kind"], "pi_r2_async", "{v}");
    assert_eq!(v["trace"]["ticks"], 25, "{v}");
    assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1, "{v}");
    assert!(v["head"].as_str().unwrap().contains("ONNX"), "{v}");

    // The same run with the head in candle, straight from the step directory.
    let candle_run = |step: &Path| {
        let _ = std::fs::remove_file(&json);
        run_emulated(&ck, Some(step), &json)
    };
    let (out, text) = candle_run(&step);
    assert!(out.status.success(), "run --candle-head: {text}");
    let v = read_json(&json);
    assert_eq!(v["mode"]["kind"], "pi_r2_async", "{v}");
    assert_eq!(v["trace"]["ticks"], 25, "{v}");
    assert!(v["head"].as_str().unwrap().contains("candle"), "{v}");
    // A step trained with other statistics than the checkpoint's: refused, naming both.
    let stats = run.join("statistics.json");
    let original = std::fs::read_to_string(&stats).unwrap();
    std::fs::write(&stats, original.replacen("0.", "0.5", 1)).unwrap();
    let (out, text) = candle_run(&step);
    eprintln!("{text}");
    assert!(!out.status.success());
    assert!(
        text.contains("statistics.json") && text.contains("differs"),
        "{text}"
    );
    assert!(!text.contains("ticks 25"), "{text}");
}

#[test]
fn bad_export_inputs_are_one_error_naming_what_is_wrong() {
    let (dir, run) = trained("gr00t-export-bad");
    let step = run.join("step-000002");
    let root = dir.path();

    // An existing, non-empty output directory: refused, the user's file untouched.
    let out = root.join("taken");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let (o, text) = export(&step, &out);
    eprintln!("{text}");
    assert!(!o.status.success());
    assert!(
        text.contains("not empty") && text.contains("taken"),
        "{text}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 1);

    // A step directory without the delay table (the base checkpoint in a run's layout).
    let base = run.join("step-base");
    std::fs::create_dir_all(&base).unwrap();
    for f in ["config.json", "model.safetensors"] {
        std::fs::copy(root.join("n17").join(f), base.join(f)).unwrap();
    }
    let (o, text) = export(&base, &root.join("out-base"));
    eprintln!("{text}");
    assert!(!o.status.success());
    assert!(
        text.contains("action_head.delay_embedding.weight") && text.contains("step-base"),
        "{text}"
    );
    assert!(!root.join("out-base").exists());

    // A mis-shaped tensor: config.json says max_action_dim 21, the weights have 20.
    let wrong = run.join("step-wrong");
    std::fs::create_dir_all(&wrong).unwrap();
    std::fs::copy(
        step.join("model.safetensors"),
        wrong.join("model.safetensors"),
    )
    .unwrap();
    let mut cfg = config_json();
    cfg["max_action_dim"] = 21.into();
    std::fs::write(wrong.join("config.json"), cfg.to_string()).unwrap();
    let (o, text) = export(&wrong, &root.join("out-wrong"));
    eprintln!("{text}");
    assert!(!o.status.success());
    assert!(
        text.contains("action_head.action_encoder.W1.W") && text.contains("21"),
        "{text}"
    );

    // A delay table of another size than the embodiment's d_vis_max.
    let other = root.join("other-run");
    let other_step = other.join("step-000002");
    std::fs::create_dir_all(&other_step).unwrap();
    for f in ["config.json", "model.safetensors"] {
        std::fs::copy(step.join(f), other_step.join(f)).unwrap();
    }
    std::fs::copy(run.join("statistics.json"), other.join("statistics.json")).unwrap();
    let mut emb = embodiment();
    emb.d_vis_max = 3;
    std::fs::write(other.join("embodiment.toml"), emb.to_toml().unwrap()).unwrap();
    let (o, text) = export(&other_step, &root.join("out-other"));
    eprintln!("{text}");
    assert!(!o.status.success());
    assert!(
        text.contains("delay table") && text.contains("[6, 16]") && text.contains("[4, 16]"),
        "{text}"
    );
    assert!(!root.join("out-other").exists());
}
