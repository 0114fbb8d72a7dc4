#!/usr/bin/env python3
"""Generates the tokenizer parity fixtures: small BPE tokenizers trained with the Rust `tokenizers`
package, a shared list of input strings, and the ids `tokenizers` / `transformers` produce for them.

Usage (inside the oracle venv): python tokenizer_fixtures.py [--out tests/fixtures/tokenizer]
Everything is deterministic (fixed seeds, single-threaded training), so regenerating gives the same files.
"""

import argparse
import json
import os
import random
import sys
import unicodedata
from pathlib import Path

os.environ.setdefault("RAYON_NUM_THREADS", "1")  # training ties break deterministically on one thread
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import tokenizers  # noqa: E402
import transformers  # noqa: E402
from tokenizers import AddedToken, Regex, Tokenizer, decoders, models, normalizers, pre_tokenizers  # noqa: E402
from tokenizers import processors, trainers  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

GPT2_PATTERN = r"'s|'t|'re|'ve|'m|'ll|'d| ?\p{L}+| ?\p{N}+| ?[^\s\p{L}\p{N}]+|\s+(?!\S)|\s+"
LLAMA3_PATTERN = (
    r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}{1,3}| ?[^\s\p{L}\p{N}]+[\r\n]*"
    r"|\s*[\r\n]+|\s+(?!\S)|\s+"
)
QWEN2_PATTERN = (
    r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*"
    r"|\s*[\r\n]+|\s+(?!\S)|\s+"
)

# ---------------------------------------------------------------------------------------------
# Text material: the training corpus and the test cases are drawn from these pools.

ENGLISH = (
    "the a an robot arm gripper picks up places red blue green yellow cube block cup bowl plate "
    "table drawer shelf left right top bottom into onto from near far slowly carefully then and "
    "open close push pull rotate lift lower move put stack sort fold towel sponge bottle lid "
    "kitchen sink counter camera wrist front view joint position velocity torque episode task "
    "don't can't won't it's they're we've I'm you'll she'd isn't THE Robot ROBOT Pick Place"
).split()

ROBOT_TASKS = [
    "Pick up the red cube and place it in the bowl.",
    "pick up the lego brick",
    "Put the cup on the plate",
    "open the top drawer and put the bowl inside",
    "Grasp a lego block and put it in the bin.",
    "stack the blue block on top of the green block",
    "Move the sponge 10 cm to the left",
    "fold the towel in half, then push it to the corner",
    "Insert the peg into hole #3 (the one on the right).",
    "rotate the knob 90 degrees clockwise",
    "Pour 250ml of water into the glass",
    "wipe the table with the cloth; avoid the laptop!",
    "sort objects: cubes -> left bin, spheres -> right bin",
    "It's the robot's turn: they're waiting, we've asked, I'm done, you'll see, he'd go",
]

MULTILINGUAL = [
    "机器人拿起红色的方块", "把杯子放在盘子上", "ロボットがカップを持ち上げる", "로봇이 컵을 집어 든다",
    "الروبوت يلتقط المكعب الأحمر", "רובוט מרים את הכוס", "रोबोट लाल घन उठाता है", "हिन्दी में निर्देश",
    "Робот берёт красный кубик", "Ο ρομπότ σηκώνει τον κύβο", "หุ่นยนต์หยิบลูกบาศก์", "Rô-bốt nhặt khối lập phương",
    "Le robot saisit le cube rouge à côté du bol", "Der Roboter hebt den Würfel über die Straße",
    "El robot coge la taza pequeña y la pone allí", "ça, où, naïve, façade, Ångström, smörgåsbord",
    "İstanbul ıIiİ ǅ ǈ ß ẞ ΣΑΣ σας ﬁ ﬀ Ⅻ ① ²³ ½",
]

EMOJI = [
    "🤖", "🦾", "👍", "👍🏽", "👩‍🔬", "👨‍👩‍👧‍👦", "🏳️‍🌈", "❤️", "🇫🇷", "🇯🇵", "✋🏿", "🧑🏻‍🤝‍🧑🏾", "🙂", "😀😃😄",
    "#️⃣", "🔟", "☕", "🍎🍏", "🚀 to 🌕",
]

NUMBERS = [
    "0", "7", "42", "123", "2024", "31415", "123456", "9876543210", "3.14159", "-17", "+1",
    "1,000,000", "1e-5", "0x1F", "v2.0.1", "12:30", "2024-06-01", "50%", "$9.99", "٣٤٥", "१२३", "१२३४",
    "１２３", "²", "⅔",
]

PUNCT = [
    "!", "?", "...", "?!", ",", ";", ":", "--", "—", "–", "(", ")", "[x]", "{y}", "<z>", "\"quoted\"",
    "'single'", "«guillemets»", "„Anführung“", "•", "@user", "#tag", "a/b", "c\\d", "x_y", "`code`",
    "~", "^", "&&", "||", "==>", "::", "©", "™", "°C", "±", "→", "∑", "√", "∞", "∂",
]

WHITESPACE = [
    " ", "  ", "   ", "\t", "\t\t", "\n", "\n\n", "\r\n", "\r", " \n ", "\n \n", "\t \t", "\u00a0",
    "\u3000", "\u2009", "\u200b", "\u2028", "\u0085", "\u180e", "\ufeff", "\u000b", "\u000c",
]

ODD_UNICODE = [
    "\ufffd", "\uffff", "\U0010ffff", "\ue000", "\U000f0000", "\u0080", "\u009f", "\ud7ff", "\u0301",
    "e\u0301", "\u00e9", "A\u030a", "\u212b", "\u1100\u1161\u11a8", "\uac01", "\u0000", "\u001b[0m",
    "\u202e", "\u2066x\u2069", "\U0001d400\U0001d401", "\U00020000", "\u0d15\u0d4d\u0d37",
]

SMOL_SPECIAL = [
    "<|endoftext|>", "<|im_start|>", "<|im_end|>", "<end_of_utterance>", "<fake_token_around_image>",
    "<image>", "<global-img>", "<row_1_col_1>", "<row_1_col_2>",
]
LLAMA_SPECIAL = ["<|begin_of_text|>", "<|end_of_text|>", "<|eot_id|>", "<|start_header_id|>", "<|end_header_id|>"]


def random_words(rng, n):
    return " ".join(rng.choice(ENGLISH) for _ in range(n))


def corpus(rng, lines=6000):
    """Training text covering every script the cases use, so merges exist for all of them."""
    out = []
    for i in range(lines):
        kind = i % 8
        if kind == 0:
            out.append(random_words(rng, rng.randint(4, 14)))
        elif kind == 1:
            out.append(rng.choice(ROBOT_TASKS))
        elif kind == 2:
            out.append(rng.choice(MULTILINGUAL))
        elif kind == 3:
            out.append(" ".join(rng.choice(NUMBERS) for _ in range(rng.randint(1, 5))))
        elif kind == 4:
            out.append(random_words(rng, 3) + rng.choice(PUNCT) + " " + rng.choice(EMOJI))
        elif kind == 5:
            out.append(rng.choice(WHITESPACE).join(rng.choice(ENGLISH) for _ in range(4)))
        elif kind == 6:
            out.append(unicodedata.normalize(rng.choice(["NFC", "NFD"]), rng.choice(MULTILINGUAL)))
        else:
            out.append(rng.choice(ENGLISH).upper() + "'s " + rng.choice(ENGLISH) + "'re " + rng.choice(ENGLISH))
    return out


def fragment(rng, specials):
    pools = [ENGLISH, ROBOT_TASKS, MULTILINGUAL, EMOJI, NUMBERS, PUNCT, WHITESPACE, ODD_UNICODE]
    weights = [6, 3, 3, 2, 3, 3, 3, 1]
    pool = rng.choices(pools, weights)[0]
    s = rng.choice(pool)
    r = rng.random()
    if r < 0.1:
        s = unicodedata.normalize("NFD", s)
    elif r < 0.15:
        s = s.upper()
    return s


def make_cases(rng, count):
    specials = SMOL_SPECIAL + LLAMA_SPECIAL + ["[ACT]", "<pad_l>", "grip", "Hello World", "[BOS]", "[EOS]"]
    fixed = [
        "", " ", "  ", "\n", "\r\n", "\t", " \t\n\r\n  x", "a", "A", "é", "e\u0301", "hello", " hello", "hello ",
        "Hello world", "Hello  world", "Hello   world  ", "  leading", "trailing  ", "\n\nnew\n\nlines\n\n",
        "it's", "It'S", "they're", "we've", "I'm", "you'll", "she'd", "don't", "'s'", "''s", "x's's",
        "'ſ", "12", "123", "1234", "12345", "123456789012", "3.14", "a1b2c3", "٣٤٥", "१२३", "１２３", "Ⅻ",
        "   \n   \n", "a\u00a0b", "a\u3000b", "a\u180eb", "a\u200bb", "a\u0085b", "\u2028\u2029",
        "<|im_start|>user\nPick up the cube<end_of_utterance>\n<|im_start|>assistant\n",
        "<fake_token_around_image><global-img><image><image><fake_token_around_image>",
        "<|im_start|><|im_start|>", "x<|im_end|>y", "<|im_start", "im_start|>", "<<|im_end|>>",
        "<image>pick up the cube\n", "text   <pad_l>   more", "[ACT]   next", "[ACT]next", "a [ACT] b",
        "grip", "grip it", "regrip", "gripper", "grip_it", "the grip.", "Hello World", "hello world",
        "HELLO WORLD", " Hello World ", "<|begin_of_text|>Hi<|eot_id|>", "<|eot_id|><|eot_id|>",
        "[BOS] raw [EOS]", "Robot", "ROBOT robot Robot", "🤖", "👨‍👩‍👧‍👦", "👍🏽👍🏿", "🇫🇷🇯🇵",
        "\ufffd\uffff\U0010ffff", "\u0000", "a" * 300, "ab" * 200, "1" * 50, " " * 40, "!" * 30,
        "supercalifragilisticexpialidocious", "pick. place, push; pull: lift-lower--rotate---",
        "...", "a.b.c", "x - y -- z", "Mr. Robot, 3.5 cm; left:right", "\t\ttabs\tand\t spaces",
        "Grab the cup. grab THE CUP.", "ﬁne ﬀ ① ²", "Ångström Å Å", "\u1100\u1161\u11a8 \uac01",
        # The crate normalises with Unicode 9.0 tables: later decompositions and combining classes
        # (U+32FF, U+1FBF0.., U+0D3B) are left alone.
        "\u32ff \U0001fbf0\U0001fbf9 \U0001f16c", "a\u0d3b\u0301 a\u0301\u0d3b", "\u0130 \u03a3 \u1e9e",
    ]
    cases = list(fixed)
    while len(cases) < count:
        n = rng.randint(1, 8)
        parts = []
        for _ in range(n):
            r = rng.random()
            if r < 0.08:
                parts.append(rng.choice(specials))
            else:
                parts.append(fragment(rng, specials))
            sep = rng.choices(["", " ", "  ", "\n", "\t", " \n"], [3, 10, 1, 1, 1, 1])[0]
            parts.append(sep)
        s = "".join(parts)
        if rng.random() < 0.05:
            s = " " + s
        if rng.random() < 0.3:
            s = s + "\n"  # lerobot appends a newline to the task
        cases.append(s)
    # Unique, order-preserving: a duplicate adds bytes without adding coverage.
    seen = set()
    unique = []
    for c in cases:
        if c not in seen:
            seen.add(c)
            unique.append(c)
    return unique, len(fixed)


# ---------------------------------------------------------------------------------------------
# Tokenizers.

def train(tok, lines, vocab_size, special_tokens, byte_level=True, limit_alphabet=None):
    kwargs = dict(vocab_size=vocab_size, special_tokens=special_tokens, show_progress=False, min_frequency=2)
    if byte_level:
        kwargs["initial_alphabet"] = pre_tokenizers.ByteLevel.alphabet()
    if limit_alphabet is not None:
        kwargs["limit_alphabet"] = limit_alphabet
    tok.train_from_iterator(lines, trainers.BpeTrainer(**kwargs))
    return tok


def build_smollm(lines, digits_in_training=True):
    """SmolLM2/SmolVLM layout. Trained without the Digits split, the vocabulary gets multi-digit
    merges, which makes the file's Digits pre-tokenizer observable (used for the GPT2Tokenizer case)."""
    tok = Tokenizer(models.BPE())
    smol_pre = pre_tokenizers.Sequence(
        [pre_tokenizers.Digits(individual_digits=True), pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=True)]
    )
    tok.pre_tokenizer = smol_pre if digits_in_training else pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    tok.post_processor = processors.ByteLevel(trim_offsets=False)
    train(tok, lines, 1200, SMOL_SPECIAL[:3])
    tok.pre_tokenizer = smol_pre
    tok.add_special_tokens([AddedToken(t, special=True, normalized=False) for t in SMOL_SPECIAL[3:]])
    tok.add_tokens(
        [
            AddedToken("<pad_l>", lstrip=True, rstrip=True, special=False, normalized=False),
            AddedToken("[ACT]", rstrip=True, special=False, normalized=False),
            AddedToken("grip", single_word=True, special=False, normalized=True),
            AddedToken("Hello World", lstrip=True, special=False, normalized=True),
        ]
    )
    return tok


def build_gpt2(lines, add_prefix_space=False):
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=add_prefix_space)
    tok.decoder = decoders.ByteLevel()
    tok.post_processor = processors.ByteLevel(trim_offsets=False)
    train(tok, lines, 1000, ["<|endoftext|>"])
    return tok


def build_llama3(lines):
    tok = Tokenizer(models.BPE(ignore_merges=True))
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(LLAMA3_PATTERN), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, trim_offsets=True, use_regex=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    train(tok, lines, 1500, LLAMA_SPECIAL)
    bos = tok.token_to_id("<|begin_of_text|>")
    tok.post_processor = processors.Sequence(
        [
            processors.ByteLevel(trim_offsets=False),
            processors.TemplateProcessing(
                single="<|begin_of_text|> $A", pair="<|begin_of_text|> $A <|begin_of_text|> $B:1",
                special_tokens=[("<|begin_of_text|>", bos)],
            ),
        ]
    )
    return tok


def build_qwen2(lines):
    tok = Tokenizer(models.BPE())
    tok.normalizer = normalizers.NFC()
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(QWEN2_PATTERN), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    tok.post_processor = processors.ByteLevel(trim_offsets=False)
    train(tok, lines, 1500, ["<|endoftext|>", "<|im_start|>", "<|im_end|>"])
    return tok


def build_misc(lines):
    """Exercises the less common components: normalizer chain, every Split behaviour, inversion."""
    tok = Tokenizer(models.BPE())
    tok.normalizer = normalizers.Sequence(
        [
            normalizers.Strip(left=True, right=True),
            normalizers.NFKC(),
            normalizers.Replace(Regex(r"\s+"), " "),
            normalizers.Lowercase(),
            normalizers.Replace("grab", "pick"),
        ]
    )
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(".", behavior="merged_with_previous"),
            pre_tokenizers.Split(Regex(r"[,;:]"), behavior="removed"),
            pre_tokenizers.Split(Regex(r"-+"), behavior="merged_with_next"),
            pre_tokenizers.Split(Regex(r"[\p{L}\p{M}]+"), behavior="contiguous", invert=True),
            pre_tokenizers.Digits(individual_digits=False),
            pre_tokenizers.ByteLevel(add_prefix_space=True, use_regex=True),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    train(tok, lines, 900, ["[BOS]", "[EOS]"])
    tok.post_processor = processors.TemplateProcessing(
        single="[BOS] $A [EOS]", special_tokens=[("[BOS]", tok.token_to_id("[BOS]")), ("[EOS]", tok.token_to_id("[EOS]"))]
    )
    tok.add_tokens(
        [
            AddedToken("Hello World", normalized=True, special=False),  # matched after lowercasing
            AddedToken("ROBOT", normalized=True, special=False, single_word=True),
            AddedToken("[ACT]", normalized=False, special=False, lstrip=True, rstrip=True),
        ]
    )
    return tok


def build_fallback(lines):
    """Character-level BPE (no byte-level pre-tokenizer) with byte_fallback, unk and fuse_unk."""
    tok = Tokenizer(models.BPE(unk_token="<unk>", fuse_unk=True, byte_fallback=True))
    tok.normalizer = normalizers.Sequence([normalizers.Prepend("▁"), normalizers.Replace(" ", "▁")])
    train(tok, lines, 700, ["<unk>", "<s>", "</s>"], byte_level=False, limit_alphabet=60)
    data = json.loads(tok.to_str())
    vocab = data["model"]["vocab"]
    next_id = max(vocab.values()) + 1
    # Byte tokens for 0x00-0xBF only: ASCII not in the alphabet falls back to bytes, while any
    # multi-byte character needs a lead byte >= 0xC2 and so falls back to <unk>.
    for b in range(0xC0):
        name = f"<0x{b:02X}>"
        if name not in vocab:
            vocab[name] = next_id
            next_id += 1
    for t in data["added_tokens"]:
        t["id"] = vocab[t["content"]]
    return Tokenizer.from_str(json.dumps(data))


def merges_as_strings(tok):
    """Older tokenizer.json files store merges as "a b" strings; keep one fixture in that form."""
    data = json.loads(tok.to_str())
    data["model"]["merges"] = [" ".join(m) if isinstance(m, list) else m for m in data["model"]["merges"]]
    return Tokenizer.from_str(json.dumps(data))


# ---------------------------------------------------------------------------------------------


def write_qwen2_vocab_merges(tok, d):
    """Writes `tok`'s BPE as vocab.json + merges.txt (the trained specials moved out of the vocabulary) and a
    tokenizer_config.json shaped like the Eagle directory's."""
    d.mkdir(exist_ok=True)
    for stale in d.iterdir():
        stale.unlink()
    trained = tok.get_vocab(with_added_tokens=False)
    specials = ["<|endoftext|>", "<|im_start|>", "<|im_end|>"]
    in_order = [t for t, _ in sorted(trained.items(), key=lambda kv: kv[1]) if t not in specials]
    vocab = {t: i for i, t in enumerate(in_order)}
    merges = json.loads(tok.to_str())["model"]["merges"]
    (d / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False, indent=2) + "\n", encoding="utf-8")
    with open(d / "merges.txt", "w", encoding="utf-8") as f:
        f.write("#version: 0.2\n")
        for m in merges:
            f.write((m if isinstance(m, str) else " ".join(m)) + "\n")
    added = specials + ["<tool_call>", "</tool_call>", "<think>", "</think>", "<IMG_CONTEXT>", "<img>", "</img>"]
    not_special = {"<tool_call>", "</tool_call>", "<think>", "</think>"}
    decoder = {
        str(len(vocab) + k): {
            "content": t, "lstrip": False, "normalized": False, "rstrip": False, "single_word": False,
            "special": t not in not_special,
        }
        for k, t in enumerate(added)
    }
    extra = ["<|im_start|>", "<|im_end|>", "<IMG_CONTEXT>", "<img>", "</img>"]
    config = {
        "add_bos_token": False, "add_eos_token": False, "add_prefix_space": False, "added_tokens_decoder": decoder,
        "additional_special_tokens": extra, "bos_token": None, "clean_up_tokenization_spaces": False,
        "eos_token": "<|im_end|>", "errors": "replace", "extra_special_tokens": {}, "model_max_length": 32768,
        "pad_token": "<|endoftext|>", "split_special_tokens": False, "tokenizer_class": "Qwen2Tokenizer",
        "unk_token": None,
    }
    (d / "tokenizer_config.json").write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")


def write_jsonl(path, rows):
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        for r in rows:
            f.write(json.dumps(r, ensure_ascii=False, separators=(",", ":")) + "\n")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(REPO / "tests/fixtures/tokenizer"))
    ap.add_argument("--cases", type=int, default=1800)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    lines = corpus(random.Random(1234))
    cases, n_fixed = make_cases(random.Random(5678), args.cases)

    gpt2_trunc = build_gpt2(lines, add_prefix_space=True)
    gpt2_trunc.enable_truncation(max_length=10, direction="left")
    gpt2_trunc.enable_padding(length=14, direction="left", pad_id=0, pad_token="<|endoftext|>")

    # name -> (tokenizer, every n-th case is used; the hand-written cases always are)
    tokenizers_by_name = {
        "smollm": (build_smollm(lines), 1),
        "gpt2": (merges_as_strings(build_gpt2(lines)), 2),
        "llama3": (build_llama3(lines), 1),
        "qwen2": (build_qwen2(lines), 2),
        "misc": (build_misc(lines), 2),
        "fallback": (build_fallback(lines), 3),
        "gpt2_trunc": (gpt2_trunc, 5),
    }

    meta = {
        "generator": "tools/oracle/tokenizer_fixtures.py",
        "tokenizers": tokenizers.__version__,
        "transformers": transformers.__version__,
        "python": sys.version.split()[0],
        "unicode": unicodedata.unidata_version,
    }
    write_jsonl(out / "cases.jsonl", [{"meta": meta}] + [{"i": i, "text": t} for i, t in enumerate(cases)])

    def expectations(encode, decode, vocab_size, stride, extra_meta=None):
        rows = [{"meta": dict(meta, vocab_size=vocab_size, special_stride=4, **(extra_meta or {}))}]
        for i in range(len(cases)):
            if i >= n_fixed and i % stride != 0:
                continue
            text = cases[i]
            plain = encode(text, False)
            special = encode(text, True)
            row = {"i": i, "ids": plain}
            # With a template the with-specials ids are kept for every 4th case only (file size).
            if special != plain and i % 4 == 0:
                row["ids_special"] = special
            if i % 4 == 0:
                row["decode"] = decode(special, False)
                row["decode_skip"] = decode(special, True)
            rows.append(row)
        return rows

    for name, (tok, stride) in tokenizers_by_name.items():
        d = out / name
        d.mkdir(exist_ok=True)
        tok.save(str(d / "tokenizer.json"), pretty=False)
        tok = Tokenizer.from_file(str(d / "tokenizer.json"))  # expectations come from the file as written
        rows = expectations(
            lambda t, sp, tok=tok: tok.encode(t, add_special_tokens=sp).ids,
            lambda ids, skip, tok=tok: tok.decode(ids, skip_special_tokens=skip),
            tok.get_vocab_size(with_added_tokens=True), stride,
        )
        write_jsonl(d / "expected.jsonl", rows)

    # A checkpoint-style directory whose tokenizer_config.json names GPT2Tokenizer, as SmolVLM's
    # does: transformers rebuilds that class's pipeline (ByteLevel only, no Digits split), so the
    # expectations come from transformers, not from tokenizer.json alone.
    d = out / "smollm_gpt2cls"
    d.mkdir(exist_ok=True)
    build_smollm(lines, digits_in_training=False).save(str(d / "tokenizer.json"), pretty=False)
    config = {
        "tokenizer_class": "GPT2Tokenizer", "backend": "tokenizers", "add_prefix_space": False,
        "bos_token": "<|im_start|>", "eos_token": "<end_of_utterance>", "pad_token": "<|im_end|>",
        "unk_token": "<|endoftext|>", "mask_token": "<mask_tok>", "extra_special_tokens": [],
        "truncation_side": "left", "clean_up_tokenization_spaces": False, "model_max_length": 8192,
    }
    (d / "tokenizer_config.json").write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")
    gpt2cls = transformers.AutoTokenizer.from_pretrained(str(d))
    assert type(gpt2cls).__name__ == "GPT2Tokenizer", type(gpt2cls)
    backend = gpt2cls.backend_tokenizer
    rows = expectations(
        lambda t, sp: gpt2cls(t, add_special_tokens=sp)["input_ids"],
        lambda ids, skip: backend.decode(ids, skip_special_tokens=skip),
        backend.get_vocab_size(with_added_tokens=True), 3,
        {"class": type(gpt2cls).__name__, "effective_pre_tokenizer": json.loads(backend.to_str())["pre_tokenizer"]},
    )
    write_jsonl(d / "expected.jsonl", rows)

    # tokenizer_config.json asking for BOS/EOS: transformers drops those flags when tokenizer.json
    # exists, but adds the named eos token, which the file lacks, as a new special token.
    d = out / "gpt2_config_flags"
    d.mkdir(exist_ok=True)
    (d / "tokenizer.json").write_bytes((out / "gpt2" / "tokenizer.json").read_bytes())
    config = {
        "tokenizer_class": "PreTrainedTokenizerFast", "bos_token": "<|endoftext|>", "eos_token": "<|eot|>",
        "add_bos_token": True, "add_eos_token": True, "padding_side": "left",
    }
    (d / "tokenizer_config.json").write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")
    flags_tok = transformers.PreTrainedTokenizerFast.from_pretrained(str(d))
    rows = expectations(
        lambda t, sp: flags_tok(t, add_special_tokens=sp)["input_ids"],
        lambda ids, skip: flags_tok.backend_tokenizer.decode(ids, skip_special_tokens=skip),
        flags_tok.backend_tokenizer.get_vocab_size(with_added_tokens=True), 10,
        {"class": type(flags_tok).__name__},
    )
    write_jsonl(d / "expected.jsonl", rows)

    # Qwen2Tokenizer saved as vocab.json + merges.txt with no tokenizer.json, laid out as GR00T N1.6's Eagle
    # directory ships it: the specials live outside vocab.json, in tokenizer_config.json's added_tokens_decoder
    # (special and non-special entries), with Eagle's image tokens. transformers builds the pipeline from the class.
    write_qwen2_vocab_merges(build_qwen2(lines), out / "qwen2_vocab_merges")
    qwen2_slow = transformers.AutoTokenizer.from_pretrained(str(out / "qwen2_vocab_merges"))
    assert type(qwen2_slow).__name__ == "Qwen2Tokenizer", type(qwen2_slow)
    rows = expectations(
        lambda t, sp: qwen2_slow(t, add_special_tokens=sp)["input_ids"],
        lambda ids, skip: qwen2_slow.backend_tokenizer.decode(ids, skip_special_tokens=skip),
        qwen2_slow.backend_tokenizer.get_vocab_size(with_added_tokens=True), 2,
        {"class": type(qwen2_slow).__name__},
    )
    write_jsonl(out / "qwen2_vocab_merges" / "expected.jsonl", rows)

    # Batches through transformers, the way lerobot's tokenizer step calls it.
    rng = random.Random(91011)
    batch_rows = [{"meta": meta}]
    pad_tokens = {"smollm": "<|im_end|>", "llama3": "<|end_of_text|>", "misc": "[EOS]", "smollm_gpt2cls": None}
    for name, pad in pad_tokens.items():
        if pad is None:
            hf = gpt2cls  # sides and pad token from its tokenizer_config.json
        else:
            hf = transformers.PreTrainedTokenizerFast(tokenizer_file=str(out / name / "tokenizer.json"), pad_token=pad)
        for k in range(12):
            texts = [cases[rng.randrange(len(cases))] + "\n" for _ in range(rng.randint(1, 5))]
            if k == 0:
                texts = ["Pick up the red cube and place it in the bowl.\n"]
            padding = ["longest", "max_length"][k % 2]
            max_length = [48, 48, 8, 3, 16, 2][k % 6] if name != "misc" else [48, 8, 3, 16][k % 4]
            add_special = k != 5
            kwargs = dict(padding=padding, max_length=max_length, truncation=True, add_special_tokens=add_special)
            if pad is not None:
                kwargs["padding_side"] = "right" if k < 8 else "left"
            enc = hf(texts, **kwargs)
            batch_rows.append(
                {
                    "tokenizer": name, "texts": texts, "padding": padding, "max_length": max_length,
                    "padding_side": kwargs.get("padding_side", hf.padding_side), "truncation_side": hf.truncation_side,
                    "pad_token_id": hf.pad_token_id, "add_special_tokens": add_special,
                    "input_ids": enc["input_ids"], "attention_mask": enc["attention_mask"],
                }
            )
    write_jsonl(out / "batch.jsonl", batch_rows)
    total = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"wrote {len(cases)} cases, {len(batch_rows) - 1} batches, {total / 1e6:.2f} MB under {out}")


if __name__ == "__main__":
    main()
