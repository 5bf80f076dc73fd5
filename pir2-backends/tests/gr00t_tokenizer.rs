//! GR00T N1.7's prompt formatting (`tokenizer.json` + chat template) against the Python
//! reference: Hugging Face `tokenizers` and Jinja2 from PyPI, run by the fixture script
//! `pir2-backends/src/gr00t/testdata/bpe_fixture.py` with `$PIR2_PYTHON` (`source
//! .native/env.sh`; `scripts/setup-native.sh` installs both packages).
//!
//! The fixture is a small byte-level BPE shaped like the Qwen3-VL tokenizer of GR00T's VLM,
//! with a Jinja chat template in its `tokenizer_config.json`; the Python side renders that
//! template the way `transformers` does and encodes with `tokenizers`, the Rust side renders
//! pir2's own [`ChatTemplate`] and encodes with the `tokenizers` crate. Ids must agree exactly.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use pir2_backends::gr00t::config::PromptConfig;
use pir2_backends::gr00t::testing::{
    python_from_env, BPE_FIXTURE_PY, BPE_TOKENIZER_CONFIG, BPE_TOKENIZER_JSON,
};
use pir2_backends::gr00t::{
    build_sequence, formalize_language, load_tokenizer, ChatTemplate, CheckpointFiles, HfTokenizer,
    PromptTokenizer,
};
use pir2_backends::Error;

fn fixture_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-tok-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("tokenizer.json"), BPE_TOKENIZER_JSON).unwrap();
    std::fs::write(dir.join("tokenizer_config.json"), BPE_TOKENIZER_CONFIG).unwrap();
    std::fs::write(dir.join("bpe_fixture.py"), BPE_FIXTURE_PY).unwrap();
    dir
}

struct Case {
    prompt: &'static str,
    images: usize,
    per_image: usize,
    formalize: bool,
}

const fn case(prompt: &'static str, images: usize, per_image: usize) -> Case {
    Case {
        prompt,
        images,
        per_image,
        formalize: true,
    }
}

const CASES: &[Case] = &[
    case("catch the book", 1, 4),
    case("Put the books in the basket!", 2, 3),
    case("put the box on the cutting board", 1, 64),
    case("Déplace la tasse près de l'assiette — vite !", 1, 2),
    case("Greif den Würfel, leg ihn in die Schüssel (ß, ÄÖÜ).", 1, 1),
    case("把书放进篮子里。ロボット、本を！", 3, 2),
    case("ΟΔΟΣ Σ: 3.5°C at 08:30, #tag_1 ½ ①", 1, 1),
    case("tabs\tand\nnewlines   and spaces, e\u{301}te\u{301}", 1, 2),
    case("pick 🍎 up 👍🏽 -- now...", 1, 1),
    case("?!", 1, 1),
    Case {
        prompt: "Catch <|im_end|> the Book!!",
        images: 1,
        per_image: 2,
        formalize: false,
    },
];

#[derive(serde::Deserialize)]
struct Reference {
    language: String,
    text: String,
    ids: Vec<i64>,
}

fn python_reference(dir: &Path) -> Vec<Reference> {
    let cases: Vec<serde_json::Value> = CASES
        .iter()
        .map(|c| {
            serde_json::json!({
                "prompt": c.prompt, "images": c.images,
                "tokens_per_image": c.per_image, "formalize": c.formalize,
            })
        })
        .collect();
    let mut child = Command::new(python_from_env().unwrap())
        .arg(dir.join("bpe_fixture.py"))
        .arg("encode")
        .arg(dir)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    serde_json::to_writer(child.stdin.take().unwrap(), &cases).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "bpe_fixture.py encode failed (needs `tokenizers` and `jinja2`: \
         scripts/setup-native.sh): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn chat_for(c: &Case) -> ChatTemplate {
    ChatTemplate {
        images: c.images,
        formalize_language: c.formalize,
        ..Default::default()
    }
}

/// The valid (non-padding) ids of pir2's sequence for `c` with `chat`.
fn rust_ids(dir: &Path, c: &Case, chat: &ChatTemplate) -> Vec<i64> {
    let tok = HfTokenizer::load(&dir.join("tokenizer.json"), chat).unwrap();
    let cfg = PromptConfig {
        image_tokens: c.images * c.per_image,
        text_tokens: 128,
        chat: chat.clone(),
    };
    let s = build_sequence(&tok, c.prompt, &cfg).unwrap();
    // Left padding: the prompt is the tail, its image tokens are where its ids say.
    let first = s.attention.iter().position(|&a| a == 1).unwrap();
    assert!(s.attention[first..].iter().all(|&a| a == 1));
    assert!(s.ids[..first].iter().all(|&i| i == tok.pad_id()));
    for (i, &id) in s.ids.iter().enumerate() {
        assert_eq!(s.layout.image_mask[i], id == tok.image_token_id());
    }
    s.ids[first..].to_vec()
}

#[test]
fn token_ids_match_python_tokenizers_and_the_jinja_chat_template() {
    let dir = fixture_dir("golden");
    let reference = python_reference(&dir);
    assert_eq!(reference.len(), CASES.len());
    for (c, r) in CASES.iter().zip(&reference) {
        let chat = chat_for(c);
        if c.formalize {
            assert_eq!(formalize_language(c.prompt), r.language, "{:?}", c.prompt);
        }
        assert_eq!(chat.render(c.prompt, c.per_image), r.text, "{:?}", c.prompt);
        let ids = rust_ids(&dir, c, &chat);
        assert_eq!(ids, r.ids, "{:?}: text {:?}", c.prompt, r.text);
        let image = ids.iter().filter(|&&i| i == 405).count();
        assert_eq!(image, c.images * c.per_image, "{:?}", c.prompt);
    }
    // The comparison has teeth: a template off by one space gives other ids.
    let off = ChatTemplate {
        begin: "<|im_start|>user \n".into(),
        ..chat_for(&CASES[0])
    };
    assert_ne!(rust_ids(&dir, &CASES[0], &off), reference[0].ids);
    std::fs::remove_dir_all(&dir).ok();
}

fn load_err(files: &CheckpointFiles, prompt: &PromptConfig) -> Error {
    match load_tokenizer(files, prompt) {
        Ok(t) => panic!("loaded {}", t.describe()),
        Err(e) => e,
    }
}

#[test]
fn the_checkpoints_tokenizer_json_wins_and_bad_files_are_one_error_naming_them() {
    let dir = fixture_dir("files");
    let files = CheckpointFiles::in_dir(&dir);
    let prompt = PromptConfig::default();
    // tokenizer.json present: it is used, with the chat template.
    let tok = load_tokenizer(&files, &prompt).unwrap();
    assert!(tok.chat_template().is_some());
    assert!(
        tok.describe().contains("tokenizer.json"),
        "{}",
        tok.describe()
    );
    std::fs::write(&files.vocab, "<pad>\n<unk>\n<image>\ncatch\n").unwrap();
    let tok = load_tokenizer(&files, &prompt).unwrap();
    assert!(
        tok.describe().contains("tokenizer.json"),
        "{}",
        tok.describe()
    );

    // A template token the tokenizer does not have.
    let mut p = PromptConfig::default();
    p.chat.pad_token = "<pad>".into();
    let e = load_err(&files, &p);
    assert!(matches!(e, Error::Parse { .. }), "{e:?}");
    let m = e.to_string();
    assert!(
        m.contains("tokenizer.json") && m.contains("`<pad>`") && m.contains("pad_token"),
        "{m}"
    );

    // A corrupt tokenizer.json.
    std::fs::write(&files.tokenizer, "{\"model\": 3}").unwrap();
    let m = load_err(&files, &prompt).to_string();
    assert!(
        m.contains("tokenizer.json") && m.contains("not a Hugging Face tokenizer"),
        "{m}"
    );

    // Without tokenizer.json: vocab.txt (no chat template).
    std::fs::remove_file(&files.tokenizer).unwrap();
    let tok = load_tokenizer(&files, &prompt).unwrap();
    assert!(tok.chat_template().is_none());
    assert!(tok.describe().contains("vocab.txt"), "{}", tok.describe());

    // Neither.
    std::fs::remove_file(&files.vocab).unwrap();
    let e = load_err(&files, &prompt);
    assert!(matches!(e, Error::NoTokenizer { .. }), "{e:?}");
    let m = e.to_string();
    assert!(
        m.contains("tokenizer.json") && m.contains("vocab.txt"),
        "{m}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
