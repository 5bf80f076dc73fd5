//! GR00T N1.7's prompt: the VLM's BPE tokenizer (`tokenizer.json`) and its chat template.
//!
//! GR00T N1.7 does not feed the instruction to its VLM (Cosmos-Reason2-2B, a Qwen3-VL-2B) as
//! bare text. Its processor
//!
//! 1. *formalises* the instruction: lower-case, then every character that is neither a word
//!    character (letter, number, `_`) nor whitespace is removed (`"Catch the book!"` →
//!    `"catch the book"`);
//! 2. builds one user turn holding the `V·T` camera images (views × frames) first and the
//!    instruction last, and renders it with the VLM's chat template, without a generation
//!    prompt:
//!    `<|im_start|>user\n` + `<|vision_start|><|image_pad|><|vision_end|>` per image +
//!    instruction + `<|im_end|>\n`;
//! 3. repeats each image's `<|image_pad|>` once per merged ViT patch of that image;
//! 4. encodes the text with the VLM's tokenizer (byte-level BPE, `tokenizer.json`), special
//!    tokens recognised as single ids, and pads a batch on the left.
//!
//! [`ChatTemplate`] holds these pieces (defaults: GR00T N1.7's) and is configurable in the
//! embodiment's `[prompt.chat]` table for checkpoints whose VLM formats turns differently;
//! [`HfTokenizer`] loads `tokenizer.json` with Hugging Face's own `tokenizers` crate. The
//! backbone's token layout ([`super::backbone::build_sequence`]) then marks the image tokens
//! where their ids are, as GR00T's backbone does (`image_mask = input_ids == image_token_id`).
//!
//! [`load_tokenizer`] picks the checkpoint's tokenizer: `tokenizer.json` when present, else
//! the older `vocab.txt` ([`VocabTokenizer`], no chat template).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use unicode_categories::UnicodeCategories;

use super::backbone::{PromptTokenizer, Sequence, VocabTokenizer};
use super::config::{CheckpointFiles, PromptConfig};
use super::error::{Gr00tError, Result};
use super::head::VlLayout;

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
            return Err(Gr00tError::Config(format!(
                "prompt.image_tokens = {image_tokens} must be a positive multiple of \
                 prompt.chat.images = {}",
                self.images
            )));
        }
        Ok(image_tokens / self.images)
    }
}

/// Token ids, mask and layout of `prompt` through `chat`'s template, with `tok`'s ids:
/// `prompt.image_tokens + prompt.text_tokens` positions, where the template and the
/// instruction must fit in `text_tokens` (a longer prompt is an error, not truncated: cutting
/// the template would feed the model a turn it never saw).
pub(crate) fn chat_sequence(
    tok: &dyn PromptTokenizer,
    chat: &ChatTemplate,
    prompt: &str,
    cfg: &PromptConfig,
) -> Result<Sequence> {
    let per_image = chat.tokens_per_image(cfg.image_tokens)?;
    let ids = tok.encode(&chat.render(prompt, per_image))?;
    let image = tok.image_token_id();
    let n_image = ids.iter().filter(|&&i| i == image).count();
    if n_image != cfg.image_tokens {
        return Err(Gr00tError::Tokenizer(format!(
            "the chat template with prompt {prompt:?} has {n_image} image tokens \
             (`{}`), prompt.image_tokens is {}",
            chat.image_token, cfg.image_tokens
        )));
    }
    let n_text = ids.len() - n_image;
    if n_text > cfg.text_tokens {
        return Err(Gr00tError::input(
            format!("text tokens of the chat template with prompt {prompt:?}"),
            format!("at most prompt.text_tokens = {}", cfg.text_tokens),
            n_text,
        ));
    }
    let t = cfg.image_tokens + cfg.text_tokens;
    let pad = t - ids.len();
    let pads = std::iter::repeat_n(tok.pad_id(), pad);
    let (ids, valid): (Vec<i64>, Vec<bool>) = match chat.padding {
        PaddingSide::Left => (
            pads.chain(ids.iter().copied()).collect(),
            (0..t).map(|i| i >= pad).collect(),
        ),
        PaddingSide::Right => {
            let n = ids.len();
            (
                ids.into_iter().chain(pads).collect(),
                (0..t).map(|i| i < n).collect(),
            )
        }
    };
    let image_mask = ids
        .iter()
        .zip(&valid)
        .map(|(&id, &v)| v && id == image)
        .collect();
    Ok(Sequence {
        attention: valid.iter().map(|&v| i64::from(v)).collect(),
        layout: VlLayout {
            image_mask,
            attention_mask: valid,
        },
        ids,
        truncated: 0,
    })
}

/// A Hugging Face `tokenizer.json` (the VLM's own BPE tokenizer) with the chat template the
/// prompt is rendered through.
pub struct HfTokenizer {
    inner: tokenizers::Tokenizer,
    path: PathBuf,
    chat: ChatTemplate,
    pad: i64,
    image: i64,
}

impl std::fmt::Debug for HfTokenizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HfTokenizer")
            .field("path", &self.path)
            .field("vocab_size", &self.inner.get_vocab_size(true))
            .field("chat", &self.chat)
            .finish()
    }
}

impl HfTokenizer {
    /// Load `tokenizer.json`; `chat`'s image and padding tokens must each be one token of it.
    pub fn load(path: &Path, chat: &ChatTemplate) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Gr00tError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let parse = |message: String| Gr00tError::Parse {
            path: path.to_path_buf(),
            message,
        };
        let inner: tokenizers::Tokenizer = text
            .parse()
            .map_err(|e| parse(format!("not a Hugging Face tokenizer: {e}")))?;
        let id = |what: &str, token: &str| {
            inner.token_to_id(token).map(i64::from).ok_or_else(|| {
                parse(format!(
                    "no token `{token}` (the embodiment's prompt.chat.{what})"
                ))
            })
        };
        Ok(HfTokenizer {
            pad: id("pad_token", &chat.pad_token)?,
            image: id("image_token", &chat.image_token)?,
            path: path.to_path_buf(),
            chat: chat.clone(),
            inner,
        })
    }

    /// The file it was loaded from.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl PromptTokenizer for HfTokenizer {
    /// Ids of `text` as the tokenizer encodes it (special tokens in the text are single ids;
    /// the tokenizer's post-processor, if any, is applied, as `transformers` does).
    fn encode(&self, text: &str) -> Result<Vec<i64>> {
        let enc = self.inner.encode(text, true).map_err(|e| {
            Gr00tError::Tokenizer(format!("`{}` encoding {text:?}: {e}", self.path.display()))
        })?;
        Ok(enc.get_ids().iter().map(|&i| i64::from(i)).collect())
    }
    fn pad_id(&self) -> i64 {
        self.pad
    }
    fn image_token_id(&self) -> i64 {
        self.image
    }
    fn chat_template(&self) -> Option<&ChatTemplate> {
        Some(&self.chat)
    }
    fn describe(&self) -> String {
        format!("`{}` with the chat template", self.path.display())
    }
}

/// The checkpoint's tokenizer: [`HfTokenizer`] on `tokenizer.json` (with `prompt.chat`) when
/// the file exists, else [`VocabTokenizer`] on `vocab.txt`; neither is one error naming both.
pub fn load_tokenizer(
    files: &CheckpointFiles,
    prompt: &PromptConfig,
) -> Result<Box<dyn PromptTokenizer>> {
    if files.tokenizer.exists() {
        Ok(Box::new(HfTokenizer::load(&files.tokenizer, &prompt.chat)?))
    } else if files.vocab.exists() {
        Ok(Box::new(VocabTokenizer::load(&files.vocab)?))
    } else {
        Err(Gr00tError::NoTokenizer {
            tokenizer: files.tokenizer.clone(),
            vocab: files.vocab.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formalize_matches_gr00t_clean_up() {
        assert_eq!(formalize_language("Catch the Book!"), "catch the book");
        assert_eq!(
            formalize_language("put it in the bowl, then wait..."),
            "put it in the bowl then wait"
        );
        assert_eq!(formalize_language("x_y 3.5°C\tÉTÉ"), "x_y 35c\tété");
        assert_eq!(formalize_language("<|image_pad|>"), "image_pad");
    }

    #[test]
    fn render_puts_images_first_and_the_instruction_last() {
        let chat = ChatTemplate {
            images: 2,
            ..Default::default()
        };
        assert_eq!(
            chat.render("Pick it up!", 2),
            "<|im_start|>user\n<|vision_start|><|image_pad|><|image_pad|><|vision_end|>\
             <|vision_start|><|image_pad|><|image_pad|><|vision_end|>pick it up<|im_end|>\n"
        );
        assert_eq!(chat.tokens_per_image(6).unwrap(), 3);
        assert!(chat.tokens_per_image(5).is_err());
        let raw = ChatTemplate {
            formalize_language: false,
            images: 0,
            ..Default::default()
        };
        assert_eq!(raw.render("A!", 0), "<|im_start|>user\nA!<|im_end|>\n");
        assert!(raw.tokens_per_image(4).is_err());
    }

    /// One id per character, specials as single ids, so the layout is easy to read.
    struct CharTok;
    impl PromptTokenizer for CharTok {
        fn encode(&self, text: &str) -> Result<Vec<i64>> {
            let mut out = Vec::new();
            let mut rest = text;
            while let Some(c) = rest.chars().next() {
                if let Some(r) = rest.strip_prefix("<|image_pad|>") {
                    out.push(-1);
                    rest = r;
                } else if let Some(i) = rest.find("|>").filter(|_| rest.starts_with("<|")) {
                    out.push(-2);
                    rest = &rest[i + 2..];
                } else {
                    out.push(c as i64);
                    rest = &rest[c.len_utf8()..];
                }
            }
            Ok(out)
        }
        fn pad_id(&self) -> i64 {
            0
        }
        fn image_token_id(&self) -> i64 {
            -1
        }
    }

    #[test]
    fn chat_sequence_pads_left_and_marks_image_ids() {
        let cfg = PromptConfig {
            image_tokens: 2,
            text_tokens: 13,
            chat: ChatTemplate::default(),
        };
        // <|im_start|> u s e r \n <|vision_start|> I I <|vision_end|> a b <|im_end|> \n
        let s = chat_sequence(&CharTok, &cfg.chat, "A-b", &cfg).unwrap();
        let n = 14;
        assert_eq!(s.ids.len(), 15);
        assert_eq!(s.ids[0], 0);
        assert_eq!(
            &s.ids[1..],
            &[-2, 117, 115, 101, 114, 10, -2, -1, -1, -2, 97, 98, -2, 10]
        );
        assert_eq!(s.attention.iter().sum::<i64>(), n);
        assert_eq!(s.attention[0], 0);
        let img: Vec<usize> = (0..15).filter(|&i| s.layout.image_mask[i]).collect();
        assert_eq!(img, vec![8, 9]);
        // Right padding keeps the prompt first.
        let right = ChatTemplate {
            padding: PaddingSide::Right,
            ..Default::default()
        };
        let s = chat_sequence(&CharTok, &right, "A-b", &cfg).unwrap();
        assert_eq!(*s.ids.last().unwrap(), 0);
        assert!(!s.layout.attention_mask[14] && s.layout.attention_mask[13]);
        // Too long for text_tokens: one error, no truncation.
        let e = chat_sequence(&CharTok, &cfg.chat, "abcdefgh", &cfg).unwrap_err();
        assert!(e.to_string().contains("prompt.text_tokens = 13"), "{e}");
    }
}
