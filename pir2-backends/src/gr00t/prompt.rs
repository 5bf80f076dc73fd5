//! What the backbone's prompt is, independent of how it is tokenised or where it comes from:
//! GR00T N1.7's chat template ([`ChatTemplate`]), the tokenizer seam ([`PromptTokenizer`]),
//! and the token sequence with its layout ([`Sequence`], [`VlLayout`]) that the backbone
//! consumes and the DiT's masks are built from. The lowest floor of the deployment stack's
//! prompt path: the embodiment config, the tokenizers, the split backbone and the head build
//! on it, and it imports none of them.

use serde::{Deserialize, Serialize};
use unicode_categories::UnicodeCategories;

use crate::error::{Error, Result};

/// Which end of the sequence padding goes to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PaddingSide {
    /// Padding first, the prompt last (GR00T's processor pads on the left).
    #[default]
    Left,
    /// The prompt first, padding last.
    Right,
}

/// The chat template around the image tokens and the instruction (see the module docs).
///
/// The rendered text is
/// `begin + (image_begin + image_token × k + image_end) × images + instruction + end`,
/// with `k = prompt.image_tokens / images` and the instruction formalised when
/// `formalize_language` is set. In `embodiment.toml`:
///
/// ```toml
/// [prompt.chat]
/// begin = "<|im_start|>user\n"
/// image_begin = "<|vision_start|>"
/// image_token = "<|image_pad|>"
/// image_end = "<|vision_end|>"
/// end = "<|im_end|>\n"
/// pad_token = "<|endoftext|>"
/// images = 1
/// formalize_language = true
/// padding = "left"
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ChatTemplate {
    /// Text before the first image: the user turn's header (a system turn, if the checkpoint
    /// was trained with one, goes here too).
    pub begin: String,
    /// Text before each image's placeholder tokens.
    pub image_begin: String,
    /// The image placeholder token (one id in the tokenizer), repeated once per image token.
    pub image_token: String,
    /// Text after each image's placeholder tokens.
    pub image_end: String,
    /// Text after the instruction: the end of the user turn.
    pub end: String,
    /// The padding token (one id in the tokenizer).
    pub pad_token: String,
    /// Image blocks in the turn (GR00T: camera views × frames); `prompt.image_tokens` is
    /// split evenly between them. pir2 feeds one frame per view, so this is the number of
    /// camera views: every slow frame must carry that many images (one `--camera` or
    /// `--frames` per view, in this order), and `backbone.onnx` receives them stacked as
    /// `pixel_values` `[images, 3, s, s]`.
    pub images: usize,
    /// Lower-case the instruction and drop what is neither a word character nor whitespace
    /// (GR00T's `formalize_language`, on by default).
    pub formalize_language: bool,
    /// Where padding goes when the prompt is shorter than the sequence.
    pub padding: PaddingSide,
}

impl Default for ChatTemplate {
    fn default() -> Self {
        ChatTemplate {
            begin: "<|im_start|>user\n".into(),
            image_begin: "<|vision_start|>".into(),
            image_token: "<|image_pad|>".into(),
            image_end: "<|vision_end|>".into(),
            end: "<|im_end|>\n".into(),
            pad_token: "<|endoftext|>".into(),
            images: 1,
            formalize_language: true,
            padding: PaddingSide::Left,
        }
    }
}

/// GR00T's instruction clean-up: lower-case, then keep only word characters (Unicode
/// letters and numbers, `_`) and whitespace — Python's `re.sub(r"[^\w\s]", "", s.lower())`.
pub fn formalize_language(text: &str) -> String {
    text.to_lowercase()
        .chars()
        .filter(|&c| {
            c == '_'
                || c.is_letter()
                || c.is_number()
                || c.is_whitespace()
                // Python's `\s` also matches the ASCII separators 0x1c..=0x1f.
                || ('\u{1c}'..='\u{1f}').contains(&c)
        })
        .collect()
}

impl ChatTemplate {
    /// The rendered text for `instruction` with `tokens_per_image` placeholders per image.
    pub fn render(&self, instruction: &str, tokens_per_image: usize) -> String {
        let language = if self.formalize_language {
            formalize_language(instruction)
        } else {
            instruction.to_string()
        };
        let mut s = String::with_capacity(
            self.begin.len()
                + self.images
                    * (self.image_begin.len()
                        + self.image_token.len() * tokens_per_image
                        + self.image_end.len())
                + language.len()
                + self.end.len(),
        );
        s.push_str(&self.begin);
        for _ in 0..self.images {
            s.push_str(&self.image_begin);
            for _ in 0..tokens_per_image {
                s.push_str(&self.image_token);
            }
            s.push_str(&self.image_end);
        }
        s.push_str(&language);
        s.push_str(&self.end);
        s
    }

    /// Placeholders per image for `image_tokens` in total (an error unless it divides).
    pub fn tokens_per_image(&self, image_tokens: usize) -> Result<usize> {
        if self.images == 0 || image_tokens % self.images != 0 {
            return Err(Error::Gr00tConfig(format!(
                "prompt.image_tokens = {image_tokens} must be a positive multiple of \
                 prompt.chat.images = {}",
                self.images
            )));
        }
        Ok(image_tokens / self.images)
    }
}

/// Turns prompt text into token ids. Implement it to plug in the model's real tokenizer.
pub trait PromptTokenizer: Send {
    /// Ids of the prompt text (no special tokens, no padding).
    fn encode(&self, text: &str) -> Result<Vec<i64>>;
    /// Id of the padding token.
    fn pad_id(&self) -> i64;
    /// Id of the image placeholder token.
    fn image_token_id(&self) -> i64;
    /// The chat template the prompt is rendered through
    /// ([`super::tokenizer::build_sequence`]); `None` (the default): image placeholders first,
    /// then the bare prompt's tokens.
    fn chat_template(&self) -> Option<&ChatTemplate> {
        None
    }
    /// What this tokenizer is, for run summaries (default: "a custom tokenizer").
    fn describe(&self) -> String {
        "a custom tokenizer".into()
    }
}

/// Token ids, attention mask and layout of one prompt (see the module docs).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Sequence {
    /// `input_ids`, length `T`.
    pub ids: Vec<i64>,
    /// `attention_mask` (1 = valid), length `T`.
    pub attention: Vec<i64>,
    /// The layout for the DiT.
    pub layout: VlLayout,
    /// Prompt tokens dropped by truncation.
    pub truncated: usize,
}

/// Which tokens of the backbone sequence are image tokens and which are valid (not padding);
/// fed to the DiT as `image_mask` / `backbone_attention_mask` when it declares them.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct VlLayout {
    /// `true` for image tokens, length `T`.
    pub image_mask: Vec<bool>,
    /// `true` for valid tokens, length `T`.
    pub attention_mask: Vec<bool>,
}
