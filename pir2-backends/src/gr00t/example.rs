//! [`write_example`]: a small, seeded, N1.7-shaped example checkpoint written in pure Rust
//! (no Python, no download), so that `pir2 gr00t run gr00t-xarm-xhand --emulate` runs on a fresh
//! clone (`pir2 gr00t example DIR`).
//!
//! The checkpoint has the layout of `docs/gr00t-contract.md` for the paper's xArm6 + XHand
//! embodiment ([`EmbodimentConfig::xarm6_xhand`], unchanged: 256 px images, 64 image + 32
//! text tokens, `H` = 50, slot 10) with **random weights**; it runs the whole stack (contract
//! checks, GR00T's image preprocessing, tokenizer and chat template, backbone, action head,
//! the real-time driver) and moves the robot meaninglessly. It is not GR00T.
//!
//! | file | what |
//! |------|------|
//! | `head/config.json`, `head/model.safetensors` | a GR00T N1.7 action head (GR00T's configuration keys and tensor names, [`example_head_config`]: 4 DiT blocks of width 32) with πR²'s delay table; `pir2 gr00t train --checkpoint DIR/head` fine-tunes it, `pir2 gr00t run --candle-head DIR/head` runs it in candle |
//! | `onnx/{state_encoder,action_encoder,dit,action_decoder}.onnx`, `pir2_gr00t.safetensors` | that head exported by [`export_gr00t_n17`] (what `pir2 gr00t export` writes) |
//! | `onnx/backbone.onnx` | a stand-in backbone ([`backbone_graph`]): token embeddings of the prompt plus a projection of the views' pooled pixels, width `D_vl` = [`EXAMPLE_D_VL`] |
//! | `tokenizer.json`, `tokenizer_config.json` | a small byte-level BPE tokenizer shaped like GR00T N1.7's Qwen3-VL tokenizer ([`super::testing::BPE_TOKENIZER_JSON`]) |
//! | `embodiment.toml`, `statistics.json`, `embodiment_id.json` | the embodiment, plausible statistics, GR00T's slot map |
//! | `README.md` | says what the directory is |
//!
//! Every weight is drawn from [`pir2_schedule::Rng`] seeded with the given seed: the same
//! seed writes the same bytes.

use std::path::{Path, PathBuf};

use candle_core::Device;

use super::config::EmbodimentConfig;
use super::n17::export::{export_gr00t_n17, WeightStorage};
use super::n17::{head_tensor_shapes, Gr00tN17Config, Gr00tN17Head, DELAY_EMBEDDING, PREFIX};
use super::testing::{statistics_json, BPE_TOKENIZER_CONFIG, BPE_TOKENIZER_JSON};
use crate::error::{Error, Result};
use crate::export::graph::{attr, GraphBuilder};
use crate::export::proto::{AttrValue, DataType, Dim};

/// Backbone width `D_vl` of the example.
pub const EXAMPLE_D_VL: usize = 64;
/// Rows of the stand-in backbone's token table (token ids are taken modulo this).
pub const EXAMPLE_VOCAB_ROWS: usize = 512;

/// The example head's `config.json`: GR00T N1.7's keys, tiny widths (`D_in` = 32, `D_vl` =
/// [`EXAMPLE_D_VL`], 4 DiT blocks alternating cross- and self-attention, 2 heads of 16), room
/// for the xArm6 + XHand's 45 state and 18 action values in GR00T's 32 embodiment slots,
/// `action_horizon` 50.
pub fn example_head_config() -> serde_json::Value {
    serde_json::json!({
        "model_type": "Gr00tN1d7",
        "action_horizon": 50,
        "add_pos_embed": true,
        "attend_text_every_n_blocks": 2,
        "backbone_embedding_dim": EXAMPLE_D_VL,
        "diffusion_model_cfg": {
            "positional_embeddings": null,
            "num_layers": 4,
            "num_attention_heads": 2,
            "attention_head_dim": 16,
            "norm_type": "ada_norm",
            "output_dim": 32,
            "interleave_self_attention": true
        },
        "hidden_size": 32,
        "input_embedding_dim": 32,
        "max_action_dim": 32,
        "max_num_embodiments": 32,
        "max_seq_len": 64,
        "max_state_dim": 64,
        "num_inference_timesteps": 4,
        "state_history_length": 1,
        "use_alternate_vl_dit": true,
        "use_vlln": true,
        "vl_self_attention_cfg": null
    })
}

/// What [`write_example`] wrote.
#[derive(Debug, Clone)]
pub struct ExampleSummary {
    /// The checkpoint directory.
    pub dir: PathBuf,
    /// The files written, relative to `dir`, in writing order.
    pub files: Vec<String>,
    /// The embodiment written to `embodiment.toml`.
    pub embodiment: EmbodimentConfig,
}

fn fail(path: &Path, message: impl std::fmt::Display) -> Error {
    Error::Example {
        path: path.to_path_buf(),
        message: message.to_string(),
    }
}

/// Uniform `±scale` values.
fn uniform(rng: &mut pir2_schedule::Rng, n: usize, scale: f32) -> Vec<f32> {
    (0..n).map(|_| rng.uniform_range(-scale, scale)).collect()
}

/// Random values for the head tensor `name` of shape `shape`: `±1/√fan_in` for weights
/// (`fan_in` the input width: the last axis of a `[out, in]` linear weight, the middle axis of
/// GR00T's per-slot `[slots, in, out]`), small biases, identity `vlln`, a small position
/// embedding and delay table.
fn init(rng: &mut pir2_schedule::Rng, name: &str, shape: &[usize]) -> Vec<f32> {
    let n: usize = shape.iter().product();
    if name == "vlln.weight" {
        return vec![1.0; n];
    }
    if name == "vlln.bias" {
        return vec![0.0; n];
    }
    if name == "position_embedding.weight" || name == DELAY_EMBEDDING {
        return uniform(rng, n, 0.02);
    }
    let fan_in = match shape {
        [_, i, _] if name.ends_with(".W") => *i,
        [_, i] => *i,
        _ => return uniform(rng, n, 0.01), // biases
    };
    uniform(rng, n, 1.0 / (fan_in as f32).sqrt())
}

/// The stand-in backbone `onnx/backbone.onnx` of the contract (`pixel_values [V, 3, s, s]`,
/// `input_ids [B, T]`, `attention_mask [B, T]` → `embeddings [B, T, D_vl]`): the token
/// embedding of each id (modulo [`EXAMPLE_VOCAB_ROWS`]) times its attention mask, plus
/// `tanh(pooled · W)` where `pooled` is the per-channel pixel mean of the views, each view
/// weighted by its position (the running sum over views, averaged), so every input and the
/// view order change the output. Weights from `rng`.
pub fn backbone_graph(
    rng: &mut pir2_schedule::Rng,
    side: usize,
    d_vl: usize,
) -> crate::export::proto::ModelProto {
    let mut g = GraphBuilder::new("backbone");
    let sym = |s: &str| Dim::Symbolic(s.into());
    let pixels = g.input(
        "pixel_values",
        DataType::Float,
        vec![
            sym("images"),
            Dim::Fixed(3),
            Dim::Fixed(side),
            Dim::Fixed(side),
        ],
    );
    let ids = g.input("input_ids", DataType::Int64, vec![sym("batch"), sym("T")]);
    let mask = g.input(
        "attention_mask",
        DataType::Int64,
        vec![sym("batch"), sym("T")],
    );
    let table = uniform(rng, EXAMPLE_VOCAB_ROWS * d_vl, 1.0);
    let table = g.weight("embed_tokens", &[EXAMPLE_VOCAB_ROWS, d_vl], &table);
    let rows = g.const_i64_scalar(EXAMPLE_VOCAB_ROWS as i64);
    let wrapped = g.op("Mod", &[&ids, &rows], vec![]);
    let tokens = g.op(
        "Gather",
        &[&table, &wrapped],
        vec![attr("axis", AttrValue::Int(0))],
    );
    let maskf = g.cast_f32(&mask);
    let masku = g.unsqueeze(&maskf, &[-1]);
    let tokens = g.mul(&tokens, &masku);
    // [V, 3] per-view channel means → running sum over views → mean: [1, 3].
    let means = g.op(
        "ReduceMean",
        &[&pixels],
        vec![
            attr("axes", AttrValue::Ints(vec![2, 3])),
            attr("keepdims", AttrValue::Int(0)),
        ],
    );
    let axis0 = g.const_i64_scalar(0);
    let running = g.op("CumSum", &[&means, &axis0], vec![]);
    let pooled = g.op(
        "ReduceMean",
        &[&running],
        vec![
            attr("axes", AttrValue::Ints(vec![0])),
            attr("keepdims", AttrValue::Int(1)),
        ],
    );
    let w = uniform(rng, 3 * d_vl, 2.0);
    let w = g.weight("pixel_proj", &[3, d_vl], &w);
    let image = g.op("MatMul", &[&pooled, &w], vec![]);
    let image = g.unary("Tanh", &image);
    let image = g.unsqueeze(&image, &[1]); // [1, 1, D_vl]
    let out = g.add(&tokens, &image);
    g.output(
        &out,
        "embeddings",
        DataType::Float,
        vec![sym("batch"), sym("T"), Dim::Fixed(d_vl)],
    );
    g.finish(vec![(
        "pir2.model".into(),
        "example stand-in backbone (random; not GR00T)".into(),
    )])
}

const README: &str = "\
# pir2 example checkpoint (random weights; not GR00T)

Written by `pir2 gr00t example`: the layout of a πR² GR00T N1.7 checkpoint for the
xArm6 + XHand embodiment (docs/gr00t-contract.md in the pir2 repository), with small random
weights drawn from the seed it was given. It exercises the whole deployment stack and moves
the robot meaninglessly: run it on the emulators only.

    pir2 gr00t run gr00t-xarm-xhand --checkpoint THIS_DIR --task \"catch the book\" \\
        --emulate --seconds 2

- `onnx/*.onnx`, `pir2_gr00t.safetensors`: the action head exported from `head/`, and a
  stand-in backbone;
- `head/`: the same head as a GR00T N1.7 checkpoint (config.json + model.safetensors), for
  `pir2 gr00t train --checkpoint THIS_DIR/head` or `pir2 gr00t run … --candle-head THIS_DIR/head`;
- `tokenizer.json`, `tokenizer_config.json`: a small BPE tokenizer shaped like the VLM's;
- `embodiment.toml`, `statistics.json`, `embodiment_id.json`: the embodiment and its
  normalisation statistics.
";

/// Write the example checkpoint into `dir` with weights drawn from `seed` (see the module
/// docs). `dir` must not exist or be empty: an existing file is never overwritten. The files
/// are written into a sibling directory first and moved into place at the end, so a failure
/// leaves nothing behind.
pub fn write_example(dir: &Path, seed: u64) -> Result<ExampleSummary> {
    if dir.exists() {
        let empty = dir.is_dir()
            && std::fs::read_dir(dir)
                .map_err(|source| Error::Read {
                    path: dir.to_path_buf(),
                    source,
                })?
                .next()
                .is_none();
        if !empty {
            return Err(fail(
                dir,
                "already exists and is not empty; choose a new directory (nothing was written)",
            ));
        }
    }
    let name = dir
        .file_name()
        .ok_or_else(|| fail(dir, "has no directory name"))?;
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| fail(&parent, format!("cannot create: {e}")))?;
    let tmp = parent.join(format!(
        ".{}.partial-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| fail(&tmp, format!("cannot remove: {e}")))?;
    }
    let written = write_into(&tmp, seed);
    let (files, embodiment) = match written {
        Ok(w) => w,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    if dir.exists() {
        // Checked empty above.
        std::fs::remove_dir(dir).map_err(|e| fail(dir, format!("cannot replace: {e}")))?;
    }
    std::fs::rename(&tmp, dir).map_err(|e| {
        let _ = std::fs::remove_dir_all(&tmp);
        fail(
            dir,
            format!("cannot move `{}` into place: {e}", tmp.display()),
        )
    })?;
    Ok(ExampleSummary {
        dir: dir.to_path_buf(),
        files,
        embodiment,
    })
}

fn write_into(dir: &Path, seed: u64) -> Result<(Vec<String>, EmbodimentConfig)> {
    let mut files = Vec::new();
    let write = |files: &mut Vec<String>, rel: &str, bytes: &[u8]| -> Result<()> {
        let p = dir.join(rel);
        if let Some(parent) = p.parent() {
            std::fs::create_dir_all(parent)
                .map_err(|e| fail(parent, format!("cannot create: {e}")))?;
        }
        std::fs::write(&p, bytes).map_err(|e| fail(&p, format!("cannot write: {e}")))?;
        files.push(rel.to_string());
        Ok(())
    };
    let emb = EmbodimentConfig::xarm6_xhand();
    emb.validate()?;

    // The head as a GR00T N1.7 checkpoint, with πR²'s delay table.
    let head_dir = dir.join("head");
    let cfg_text =
        serde_json::to_string_pretty(&example_head_config()).map_err(|e| fail(&head_dir, e))?;
    write(&mut files, "head/config.json", cfg_text.as_bytes())?;
    let cfg_path = head_dir.join("config.json");
    let cfg =
        Gr00tN17Config::from_json_str(&cfg_text, &cfg_path).map_err(|e| candle(&cfg_path, e))?;
    if cfg.action_horizon != emb.horizon
        || cfg.max_state_dim < emb.state_dim()
        || cfg.max_action_dim < emb.action_dim()
        || cfg.max_num_embodiments as i64 <= emb.embodiment_id
    {
        return Err(fail(
            &cfg_path,
            "the example head does not fit the embodiment",
        ));
    }
    let mut rng = pir2_schedule::Rng::derive(seed, 0);
    let mut shapes = head_tensor_shapes(&cfg);
    shapes.push((
        DELAY_EMBEDDING.to_string(),
        vec![emb.d_vis_max + 1, cfg.input_embedding_dim],
    ));
    let tensors: Vec<(String, Vec<usize>, Vec<f32>)> = shapes
        .into_iter()
        .map(|(name, shape)| {
            let v = init(&mut rng, &name, &shape);
            (format!("{PREFIX}{name}"), shape, v)
        })
        .collect();
    let weights = head_dir.join("model.safetensors");
    crate::checkpoint::write_tensors(
        &weights,
        tensors
            .iter()
            .map(|(n, s, d)| (n.clone(), s.clone(), d.as_slice())),
    )
    .map_err(|e| fail(&weights, e))?;
    files.push("head/model.safetensors".into());
    drop(tensors);

    // Its export: the four head graphs and the side weights.
    let head = Gr00tN17Head::load(&head_dir, &Device::Cpu).map_err(|e| candle(&head_dir, e))?;
    let exported = export_gr00t_n17(&head, emb.horizon).map_err(|e| fail(&head_dir, e))?;
    drop(head);
    files.extend(
        exported
            .write(dir, WeightStorage::Inline)
            .map_err(|e| fail(dir, e))?,
    );

    // The stand-in backbone, the tokenizer, the embodiment and its statistics.
    let mut rng = pir2_schedule::Rng::derive(seed, 1);
    let bb = backbone_graph(&mut rng, emb.image.pixel_side(), cfg.backbone_embedding_dim);
    write(&mut files, "onnx/backbone.onnx", &bb.encode())?;
    write(&mut files, "tokenizer.json", BPE_TOKENIZER_JSON.as_bytes())?;
    write(
        &mut files,
        "tokenizer_config.json",
        BPE_TOKENIZER_CONFIG.as_bytes(),
    )?;
    write(&mut files, "embodiment.toml", emb.to_toml()?.as_bytes())?;
    write(
        &mut files,
        "statistics.json",
        statistics_json(&emb, None).as_bytes(),
    )?;
    let ids = serde_json::json!({ &emb.embodiment_tag: emb.embodiment_id }).to_string();
    write(&mut files, "embodiment_id.json", ids.as_bytes())?;
    write(&mut files, "README.md", README.as_bytes())?;
    Ok((files, emb))
}

fn candle(path: &Path, e: Error) -> Error {
    Error::Gr00tCandle {
        path: path.to_path_buf(),
        source: Box::new(e),
    }
}
