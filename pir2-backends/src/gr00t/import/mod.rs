//! `pir2 gr00t import`: a GR00T N1.7 checkpoint directory, as Isaac-GR00T writes and NVIDIA
//! releases it, to the checkpoint layout `pir2 gr00t run` and `pir2 gr00t train` read
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
//! `pir2_gr00t.safetensors` (`n17::export`: the head's own delay table
//! `action_head.delay_embedding.weight` when it has one, else a zero table, exactly GR00T's
//! head; πR²'s per-position AdaLN heads `<layer>_heads.*` when it has them),
//! `embodiment.toml` (mapped; `[policy] trained` is [`ImportOptions::trained`], else `"pi_r2"`
//! with `mode = "pir2_async"` for a head with per-position heads, a πR² head fine-tuned
//! elsewhere, and `"flow"` with `mode = "sync_flow"` for one without, a released GR00T
//! head), `statistics.json`, `embodiment_id.json` and
//! `processor_config.json` (copied), the VLM tokenizer when the checkpoint has one, and, with
//! [`ImportOptions::backbone_onnx`], GR00T's exported ViT and LLM graphs (bfloat16 ones
//! rewritten to float32 by [`crate::gr00t::onnx_f32`] unless [`ImportOptions::keep_bf16`]).
//!
//! Every field of the GR00T files either maps, is known to be training-only (ignored, listed
//! in the docs), or is refused: one [`crate::Error::Import`] naming the file and the field
//! (JSON path), before anything is written. The files are written to a hidden sibling of the
//! output directory and moved into place at the end.
//!
//! Three files, by what they do: `read.rs` reads Isaac-GR00T's files (JSON values carrying
//! their file and field into every error), `plan.rs` maps and checks everything GR00T's files
//! say (nothing is written yet), `write.rs` writes our layout and moves it into place.

mod plan;
mod read;
mod write;

pub use plan::{ImportOptions, N17_VLM};
pub use read::{CONFIG_FILE, EMBODIMENT_ID_FILE, PROCESSOR_FILE, STATISTICS_FILE};
pub use write::{import_checkpoint, ImportSummary, MissingFile};
