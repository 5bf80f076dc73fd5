"""The GR00T tokenizer fixture and its Python reference (Hugging Face `tokenizers` + Jinja2).

    bpe_fixture.py train OUTDIR   write OUTDIR/tokenizer.json and OUTDIR/tokenizer_config.json
    bpe_fixture.py encode DIR     read cases (JSON) on stdin, print the reference ids (JSON)

`train` fits a small byte-level BPE (400 tokens) on a fixed corpus, shaped like the
Qwen3-VL tokenizer GR00T N1.7's backbone uses: NFC normaliser, a regex split with look-ahead
followed by byte-level mapping, special tokens appended after the learned vocabulary. The
output is committed (`tokenizer.json`, `tokenizer_config.json` next to this script); run it
again only to change the fixture (training is deterministic: same corpus, same file).

`encode` is the reference pir2's Rust prompt formatting is compared against
(`pir2-backends/tests/gr00t_tokenizer.rs`). For each case
`{"prompt": str, "images": int, "tokens_per_image": int, "formalize": bool}` it follows
GR00T N1.7's processor: (if `formalize`) lower-case the instruction and drop every character
that is neither a word character nor whitespace (Python's `re` `[^\\w\\s]`), build a one-turn user conversation with the images
first and the instruction last, render it with the `chat_template` of
`tokenizer_config.json` the way `transformers` renders chat templates (sandboxed Jinja2,
`trim_blocks`, `lstrip_blocks`, no generation prompt), repeat each image placeholder
`tokens_per_image` times (as the Qwen3-VL processor does for the image's merged patches) and
encode the text with `tokenizers`. Prints `[{"language", "text", "ids"}]`.
"""

import json
import re
import sys

SPECIALS = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|image_pad|>",
]

# The split pattern of the Qwen2/Qwen3 tokenizers (contractions, letters with one leading
# non-letter, single digits, punctuation runs, newlines, trailing-space look-ahead).
SPLIT = (
    r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*"
    r"|\s*[\r\n]+|\s+(?!\S)|\s+"
)

# A chat template with the structure of Qwen3-VL's for one user turn (images, then text),
# written for this fixture.
CHAT_TEMPLATE = (
    "{%- for message in messages %}\n"
    "{{- '<|im_start|>' + message.role + '\\n' }}\n"
    "{%- if message.content is string %}\n"
    "{{- message.content }}\n"
    "{%- else %}\n"
    "{%- for part in message.content %}\n"
    "{%- if part.type == 'image' %}\n"
    "{{- '<|vision_start|><|image_pad|><|vision_end|>' }}\n"
    "{%- elif part.type == 'text' %}\n"
    "{{- part.text }}\n"
    "{%- endif %}\n"
    "{%- endfor %}\n"
    "{%- endif %}\n"
    "{{- '<|im_end|>\\n' }}\n"
    "{%- endfor %}\n"
    "{%- if add_generation_prompt %}\n"
    "{{- '<|im_start|>assistant\\n' }}\n"
    "{%- endif %}\n"
)

CORPUS = [
    "catch the book",
    "put the books in the basket",
    "put the ball in the bowl",
    "put the box on the cutting board",
    "pick up the red cup and place it on the plate",
    "open the drawer, then close it again.",
    "Grasp the handle; rotate it 90 degrees!",
    "move the block to the left of the bowl",
    "stack the green cube on top of the blue cube",
    "wipe the table with the sponge",
    "pour water into the glass",
    "hand me the screwdriver, please",
    "the robot's gripper isn't closed",
    "Déplace la tasse près de l'assiette",
    "Greif den Würfel und leg ihn in die Schüssel",
    "把书放进篮子里",
    "ロボットが本をつかむ",
    "temperature 21.5 °C at 08:30",
    "user assistant system image vision",
]


def train(out):
    from tokenizers import Regex, Tokenizer, decoders, models, normalizers, pre_tokenizers
    from tokenizers import processors, trainers

    tok = Tokenizer(models.BPE())
    tok.normalizer = normalizers.NFC()
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(SPLIT), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    tok.post_processor = processors.ByteLevel(trim_offsets=False)
    trainer = trainers.BpeTrainer(
        vocab_size=400,
        min_frequency=1,
        show_progress=False,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
    )
    tok.train_from_iterator(CORPUS * 4, trainer)
    tok.add_special_tokens(SPECIALS)
    tok.save(f"{out}/tokenizer.json", pretty=True)
    config = {
        "tokenizer_class": "Qwen2Tokenizer",
        "pad_token": "<|endoftext|>",
        "chat_template": CHAT_TEMPLATE,
    }
    with open(f"{out}/tokenizer_config.json", "w", encoding="utf-8") as f:
        json.dump(config, f, indent=2, ensure_ascii=False)
        f.write("\n")


def encode(directory):
    import jinja2.ext
    from jinja2.sandbox import ImmutableSandboxedEnvironment
    from tokenizers import Tokenizer

    tok = Tokenizer.from_file(f"{directory}/tokenizer.json")
    with open(f"{directory}/tokenizer_config.json", encoding="utf-8") as f:
        template_text = json.load(f)["chat_template"]
    env = ImmutableSandboxedEnvironment(
        trim_blocks=True, lstrip_blocks=True, extensions=[jinja2.ext.loopcontrols]
    )
    template = env.from_string(template_text)
    out = []
    for case in json.load(sys.stdin):
        prompt = case["prompt"]
        language = re.sub(r"[^\w\s]", "", prompt.lower()) if case["formalize"] else prompt
        content = [{"type": "image"} for _ in range(case["images"])]
        content.append({"type": "text", "text": language})
        text = template.render(
            messages=[{"role": "user", "content": content}], add_generation_prompt=False
        )
        text = text.replace("<|image_pad|>", "<|image_pad|>" * case["tokens_per_image"])
        ids = tok.encode(text).ids
        out.append({"language": language, "text": text, "ids": ids})
    json.dump(out, sys.stdout, ensure_ascii=False)


if __name__ == "__main__":
    {"train": train, "encode": encode}[sys.argv[1]](sys.argv[2])
