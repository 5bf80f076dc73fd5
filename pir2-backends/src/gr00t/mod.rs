//! Everything GR00T, cut by what it is:
//!
//! - [`n17`] (feature `candle`): N1.7's action head in candle, loaded from a GR00T checkpoint,
//!   with πR²'s per-position timesteps and AdaLN heads; beside it its ONNX exporter
//!   (`n17::export`) and its πR² fine-tuning trainer (`n17::train`);
//! - the xArm6 + XHand deployment stack (feature `gr00t`), below.
//!
//! # The deployment stack (feature `gr00t`)
//!
//! No weights ship with pir2: this module runs a user's export of a πR²-fine-tuned GR00T N1.7
//! checkpoint through ONNX Runtime, following the split of GR00T's own exporter
//! (`scripts/deployment/export_onnx_n1d7.py`, mode `action_head` / `full_pipeline`) with the
//! πR² changes. The full contract is in `docs/gr00t-contract.md`; in short:
//!
//! | file | inputs | output |
//! |------|--------|--------|
//! | `onnx/state_encoder.onnx`  | `state f32 [B,1,S_in]`, `embodiment_id i64 [B]` | `output [B,1,D_in]` |
//! | `onnx/action_encoder.onnx` | `actions f32 [B,H,A_max]`, **`timesteps i64 [B,H]`**, `embodiment_id` | `output [B,H,D_in]` |
//! | `onnx/dit.onnx`            | `sa_embs [B,1+H,D_in]`, `vl_embs [B,T*,D_vl]`, **`timestep i64 [B,1+H]`**, opt. `image_mask`/`backbone_attention_mask bool [B,T*]` | `output [B,1+H,D_hid]` |
//! | `onnx/action_decoder.onnx` | `model_output [B,1+H,D_hid]`, `embodiment_id` | `output [B,1+H,A_max]` |
//! | `onnx/backbone.onnx`       | `pixel_values f32 [B,3,crop,crop]`, `input_ids i64 [B,T*]`, opt. `attention_mask` | `embeddings [B,T*,D_vl]` |
//! | or `onnx/vit_{fp32,bf16}.onnx` + `onnx/llm_{fp32,bf16}.onnx` + `model.safetensors` | GR00T's own split export, glued in Rust (`split`); float tensors f32, bf16 or f16 | |
//! | `onnx/vl_self_attention.onnx` (optional) | `hidden_states [B,T*,D_vl]` | `output [B,T*,D_vl]` |
//!
//! (`*`: may be dynamic.) Bold = the πR² change: timesteps per position instead of per sample
//! (per-position AdaLN). The delay table `delay_embedding.weight [d_vis_max+1, D_in]` lives in
//! `pir2_gr00t.safetensors` and is added to the action tokens in Rust before the DiT, with
//! GR00T's position embedding (also outside ONNX in GR00T's pipeline).
//!
//! Every file is checked on load (`contract`): names, element types, ranks, static
//! dimensions, and named sizes across files (`D_in` of the state encoder = `D_in` of the DiT…);
//! errors name the file and the tensor.
//!
//! Pieces:
//! - `config`: the embodiment (`EmbodimentConfig::xarm6_xhand`), GR00T statistics,
//!   checkpoint layout;
//! - `head`: `Gr00tActionHead`, a `pir2_runtime::VelocityModel`;
//! - `candle_head` (feature `candle`): `Gr00tCandleHead`, the same interface over the candle
//!   N1.7 head of a `pir2 gr00t train` step directory (no ONNX head graphs);
//! - `backbone`: `Gr00tBackbone` (a `pir2_runtime::SlowEncoder`), image preprocessing,
//!   the `PromptTokenizer` seam and `VocabTokenizer`;
//! - `tokenizer`: the VLM's `tokenizer.json` (`HfTokenizer`) and GR00T N1.7's chat
//!   template (`ChatTemplate`);
//! - `split`: GR00T's own ViT + LLM export glued in Rust (`split::SplitBackbone`:
//!   patches, token embedding, image-token scatter, multimodal positions, deepstack);
//! - `run`: `run_gr00t`, the library side of `pir2 gr00t run gr00t-xarm-xhand`;
//! - `example` (feature `candle`): `write_example`, the seeded N1.7-shaped example checkpoint
//!   of `pir2 gr00t example`, written in pure Rust;
//! - `import` (with `candle`): a GR00T N1.7 checkpoint as Isaac-GR00T writes it
//!   (`config.json`, safetensors, `processor_config.json`, `statistics.json`,
//!   `embodiment_id.json`) to this layout (`pir2 gr00t import`, `docs/gr00t-import.md`);
//! - `onnx_f32`: NVIDIA's bfloat16 ONNX exports rewritten to float32 on the protobuf, for
//!   ONNX Runtime's CPU provider;
//! - `testing`: a tiny synthetic checkpoint and camera for tests and emulated runs.

#[cfg(feature = "candle")]
pub mod n17;

#[cfg(feature = "gr00t")]
pub mod backbone;
#[cfg(all(feature = "gr00t", feature = "candle"))]
pub mod candle_head;
#[cfg(feature = "gr00t")]
pub mod config;
#[cfg(feature = "gr00t")]
pub mod contract;
#[cfg(all(feature = "gr00t", feature = "candle"))]
pub mod example;
#[cfg(feature = "gr00t")]
pub mod head;
#[cfg(feature = "gr00t")]
pub mod image;
#[cfg(all(feature = "gr00t", feature = "candle"))]
pub mod import;
#[cfg(feature = "gr00t")]
pub mod onnx_f32;
#[cfg(feature = "gr00t")]
pub mod prompt;
#[cfg(feature = "gr00t")]
pub mod run;
#[cfg(feature = "gr00t")]
pub mod split;
#[cfg(feature = "gr00t")]
pub mod testing;
#[cfg(feature = "gr00t")]
pub mod tokenizer;
#[cfg(feature = "gr00t")]
pub mod weights;

#[cfg(feature = "gr00t")]
pub use backbone::{preprocess_image, Gr00tBackbone};
#[cfg(all(feature = "gr00t", feature = "candle"))]
pub use candle_head::Gr00tCandleHead;
#[cfg(feature = "gr00t")]
pub use config::{
    policy_name, ActionLimits, BackboneForm, CheckpointFiles, DeployKind, EmbodimentConfig, Group,
    GroupFormat, GroupLimits, ImageConfig, ImagePipeline, ModeOverrides, Norm, Normalizer,
    PolicySection, SafetySection, VisionConfig, DEFAULT_SLOW_GRACE_MS, EMBED_TOKENS_KEY,
    PAPER_TASKS,
};
#[cfg(all(feature = "gr00t", feature = "candle"))]
pub use example::{write_example, ExampleSummary};
#[cfg(feature = "gr00t")]
pub use head::{prepare_record_dir, Gr00tActionHead, HeadDims, NfeRecorder, VlLayout};
#[cfg(feature = "gr00t")]
pub use prompt::{PromptTokenizer, Sequence};
#[cfg(all(feature = "gr00t", feature = "candle"))]
pub use run::load_candle_head;
#[cfg(feature = "gr00t")]
pub use run::{
    load_action_head, run_gr00t, run_gr00t_report, BackboneChoice, Gr00tRunOptions, Gr00tRunReport,
    HeadChoice,
};
#[cfg(feature = "gr00t")]
pub use tokenizer::{
    build_sequence, formalize_language, load_tokenizer, ChatTemplate, HfTokenizer, PaddingSide,
    VocabTokenizer,
};
