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
//! backbone's token layout ([`build_sequence`]) then marks the image tokens
//! where their ids are, as GR00T's backbone does (`image_mask = input_ids == image_token_id`).
//!
//! [`load_tokenizer`] picks the checkpoint's tokenizer: `tokenizer.json` when present, else
//! the older `vocab.txt` ([`VocabTokenizer`], no chat template).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::config::{CheckpointFiles, PromptConfig};
pub use super::prompt::{
    formalize_language, ChatTemplate, PaddingSide, PromptTokenizer, Sequence, VlLayout,
};
use crate::error::{Error, Result};

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
        return Err(Error::Tokenizer(format!(
            "the chat template with prompt {prompt:?} has {n_image} image tokens \
             (`{}`), prompt.image_tokens is {}",
            chat.image_token, cfg.image_tokens
        )));
    }
    let n_text = ids.len() - n_image;
    if n_text > cfg.text_tokens {
        return Err(Error::input(
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
        let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let parse = |message: String| Error::Parse {
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
            Error::Tokenizer(format!("`{}` encoding {text:?}: {e}", self.path.display()))
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
        Err(Error::NoTokenizer {
            tokenizer: files.tokenizer.clone(),
            vocab: files.vocab.clone(),
        })
    }
}

/// A vocabulary-file tokenizer: one token per line, id = line number (0-based).
///
/// Text is lower-cased and split on whitespace, with ASCII punctuation as separate tokens;
/// a word missing from the vocabulary is split greedily into the longest known prefix and
/// `##`-continuations (WordPiece), else it becomes `<unk>`. The file must contain `<pad>`,
/// `<unk>` and `<image>`.
#[derive(Debug, Clone)]
pub struct VocabTokenizer {
    source: PathBuf,
    vocab: HashMap<String, i64>,
    pad: i64,
    unk: i64,
    image: i64,
}

impl VocabTokenizer {
    /// Special tokens that must be present.
    pub const SPECIALS: [&'static str; 3] = ["<pad>", "<unk>", "<image>"];

    /// Read a vocabulary file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_lines(text.lines(), path)
    }

    /// Build from lines (`path` names the source in errors).
    pub fn from_lines<'a>(lines: impl Iterator<Item = &'a str>, path: &Path) -> Result<Self> {
        let mut vocab = HashMap::new();
        for (i, l) in lines.enumerate() {
            let tok = l.trim_end_matches(['\r', '\n']);
            if !tok.is_empty() {
                vocab.entry(tok.to_string()).or_insert(i as i64);
            }
        }
        let get = |t: &str| {
            vocab.get(t).copied().ok_or_else(|| Error::Parse {
                path: path.to_path_buf(),
                message: format!("vocabulary has no `{t}` token (needs {:?})", Self::SPECIALS),
            })
        };
        Ok(VocabTokenizer {
            source: path.to_path_buf(),
            pad: get("<pad>")?,
            unk: get("<unk>")?,
            image: get("<image>")?,
            vocab,
        })
    }

    fn word(&self, w: &str, out: &mut Vec<i64>) {
        if let Some(&id) = self.vocab.get(w) {
            out.push(id);
            return;
        }
        let chars: Vec<(usize, char)> = w.char_indices().collect();
        let mut start = 0;
        let mut pieces = Vec::new();
        while start < chars.len() {
            let mut end = chars.len();
            let mut found = None;
            while end > start {
                let a = chars[start].0;
                let b = if end < chars.len() {
                    chars[end].0
                } else {
                    w.len()
                };
                let piece = if start == 0 {
                    w[a..b].to_string()
                } else {
                    format!("##{}", &w[a..b])
                };
                if let Some(&id) = self.vocab.get(&piece) {
                    found = Some(id);
                    break;
                }
                end -= 1;
            }
            match found {
                Some(id) => {
                    pieces.push(id);
                    start = end;
                }
                None => {
                    out.push(self.unk);
                    return;
                }
            }
        }
        out.extend(pieces);
    }
}

impl PromptTokenizer for VocabTokenizer {
    fn encode(&self, text: &str) -> Result<Vec<i64>> {
        let mut out = Vec::new();
        let lower = text.to_lowercase();
        for raw in lower.split_whitespace() {
            let mut cur = String::new();
            for c in raw.chars() {
                if c.is_ascii_punctuation() {
                    if !cur.is_empty() {
                        self.word(&cur, &mut out);
                        cur.clear();
                    }
                    self.word(&c.to_string(), &mut out);
                } else {
                    cur.push(c);
                }
            }
            if !cur.is_empty() {
                self.word(&cur, &mut out);
            }
        }
        Ok(out)
    }
    fn pad_id(&self) -> i64 {
        self.pad
    }
    fn image_token_id(&self) -> i64 {
        self.image
    }
    fn describe(&self) -> String {
        format!("vocabulary `{}` (no chat template)", self.source.display())
    }
}

/// The backbone's token sequence for `prompt`: through the tokenizer's chat template when it
/// has one (GR00T N1.7: see [`super::tokenizer`]; `T = image_tokens + text_tokens` positions,
/// padded on the template's side, a prompt too long for `text_tokens` is an error), else
/// `[image placeholder × image_tokens] + prompt tokens`, padded/truncated to `text_tokens`.
pub fn build_sequence(
    tok: &dyn PromptTokenizer,
    prompt: &str,
    cfg: &PromptConfig,
) -> Result<Sequence> {
    if let Some(chat) = tok.chat_template() {
        return chat_sequence(tok, chat, prompt, cfg);
    }
    let text = tok.encode(prompt)?;
    let n = text.len().min(cfg.text_tokens);
    let t = cfg.image_tokens + cfg.text_tokens;
    let mut ids = vec![tok.image_token_id(); cfg.image_tokens];
    ids.extend_from_slice(&text[..n]);
    ids.resize(t, tok.pad_id());
    let valid = cfg.image_tokens + n;
    let attention: Vec<i64> = (0..t).map(|i| i64::from(i < valid)).collect();
    let layout = VlLayout {
        image_mask: (0..t).map(|i| i < cfg.image_tokens).collect(),
        attention_mask: (0..t).map(|i| i < valid).collect(),
    };
    Ok(Sequence {
        ids,
        attention,
        layout,
        truncated: text.len() - n,
    })
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
