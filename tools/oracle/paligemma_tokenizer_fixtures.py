#!/usr/bin/env python3
"""Generates tests/fixtures/tokenizer/paligemma: the PaliGemma tokenizer pi0 / pi0.5 load, and upstream's ids.

lerobot 0.6.1's pi0 and pi0.5 pre-processors call `AutoTokenizer.from_pretrained("google/paligemma-3b-pt-224")`
and then the tokenizer with padding="max_length", max_length (48 for pi0, 200 for pi0.5), truncation=True,
padding_side="right". The real repository is gated, so `paligemma_tokenizer.py` trains a stand-in with Gemma's
SentencePiece settings and writes it into a hub cache under the real repository id; this script loads it from there
through AutoTokenizer exactly as lerobot does and records:

- the repository's files (tokenizer.model, tokenizer.json, tokenizer_config.json, config.json);
- expected.jsonl: for every string of the corpus, the ids with and without special tokens and the decoded text,
  once through tokenizer.json (the route the hub repository takes) and once through a copy of the directory that
  has tokenizer.model but no tokenizer.json (transformers converts the SentencePiece model), plus, for information,
  the ids SentencePiece itself gives (not what transformers runs);
- batch.jsonl: batch calls the way lerobot's TokenizerProcessorStep makes them (pi0's task + "\\n" at 48, pi0.5's
  "Task: ..., State: ...;\\nAction: " prompts built by lerobot's own step at 200) and a few other settings;
- variants.jsonl: other tokenizer_config.json contents (add_bos_token / add_eos_token, padding side, no extra
  special tokens) applied to either route, each with upstream's ids;
- decoders.jsonl: the decoders (Replace, ByteFallback, Fuse, Strip, Sequence) of the `tokenizers` package on
  token lists no encoding produces.

Usage: tools/oracle/run.sh paligemma_tokenizer_fixtures.py [--out tests/fixtures/tokenizer/paligemma]
Deterministic (single-threaded SentencePiece training, fixed seeds): regenerating gives the same files.
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import sentencepiece as spm
import tokenizers
import torch
import transformers
from transformers import AutoTokenizer

import paligemma_tokenizer
import tokenizer_fixtures as tf

REPO = Path(__file__).resolve().parents[2]
FILES = ["tokenizer.model", "tokenizer.json", "tokenizer_config.json", "config.json"]
MODEL_ONLY = ["tokenizer.model", "tokenizer_config.json", "config.json"]

SPECIALS = ["<pad>", "<eos>", "<bos>", "<unk>", "<mask>", "<start_of_turn>", "<end_of_turn>"]

FIXED = [
    "", " ", "  ", "   ", "\n", "\n\n", "\t", "\r\n", " \t\n", "x", "X", "a", "é", "e\u0301",
    "pick up the cube", " pick up the cube", "pick up the cube ", "  pick  up   the    cube  ",
    "pick\tup\tthe\tcube", "\tpick up", "pick up\n", "pick up the cube\n", "line one\nline two\n\nline four",
    "trailing spaces   ", "   leading spaces", "mixed \t \n whitespace \r\n end",
    "0", "7", "12", "127", "128", "255", "1234567890", "3.14159", "-1 0 +1", "12 127 128 0 255",
    "café au lait", "naïve résumé à la carte", "Ångström über straße", "São Paulo ñandú",
    "日本語のロボット", "机器人拿起红色的方块", "로봇이 컵을 집어 든다", "ロボット", "中文 and English mixed",
    "🤖 pick up the 🍎", "🙂", "👨‍👩‍👧‍👦", "🇫🇷", "☕ then 🚀",
    "xylophone", "QUIZ", "zebra jazz", "quixotic vex", "Xx Zz Qq Jj",
    "\u0000", "\u001b[0m", "\ufffd", "\U0010ffff", "\ue000", "\u200b", "\u00a0", "\u3000",
    "\u2581", "\u2581\u2581pick", "a\u2581b c", "\u2581 \u2581",
    "<0x41>", "<0x0A>", "<0xZZ>", "<0x41><0x42>",
    "<eos>", "<bos>", "<pad>", "<unk>", "<mask>", "<start_of_turn>", "<end_of_turn>",
    "a<eos>b", " <bos> ", "<eos><eos>", "<eos", "eos>", "<<eos>>", "< eos >", "<EOS>",
    "<start_of_turn>user\npick up the cube<end_of_turn>\n<start_of_turn>model\n",
    "text <unk> more <mask> end", "<pad><pad>pick",
    "Task: pick up the cube, State: 12 127 128 0 255;\nAction: ",
    "Task: , State: ;\nAction: ",
    "pick up the red cube and place it in the bowl " * 12,
    "a" * 300, "ab " * 150, "1" * 64, " " * 40, "\n" * 10, "!" * 30,
]


def corpus() -> list[str]:
    texts = list(FIXED)
    texts += paligemma_tokenizer.CORPUS
    texts += [t + "\n" for t in paligemma_tokenizer.CORPUS[:8]]  # pi0 appends a newline
    for pool in (tf.ROBOT_TASKS, tf.MULTILINGUAL, tf.EMOJI, tf.NUMBERS, tf.PUNCT, tf.WHITESPACE, tf.ODD_UNICODE):
        texts += pool
    rng = random.Random(4321)
    pools = [tf.ENGLISH, tf.ROBOT_TASKS, tf.MULTILINGUAL, tf.EMOJI, tf.NUMBERS, tf.PUNCT, tf.WHITESPACE, SPECIALS]
    while len(texts) < 320:
        parts = []
        for _ in range(rng.randint(1, 7)):
            parts.append(rng.choice(rng.choices(pools, [6, 3, 2, 2, 3, 2, 2, 1])[0]))
            parts.append(rng.choices(["", " ", "  ", "\n", "\t"], [2, 10, 1, 1, 1])[0])
        texts.append("".join(parts))
    seen, unique = set(), []
    for t in texts:
        if t not in seen:
            seen.add(t)
            unique.append(t)
    return unique


def pi05_prompts(tasks: list[str], rng: np.random.Generator) -> list[str]:
    """lerobot's own pi0.5 prompt step on random normalised states (32 dims, as max_state_dim)."""
    from lerobot.policies.pi05.processor_pi05 import Pi05PrepareStateTokenizerProcessorStep
    from lerobot.lerobot_types import TransitionKey
    from lerobot.utils.constants import OBS_STATE

    state = torch.from_numpy(rng.uniform(-1.2, 1.2, size=(len(tasks), 32)).astype(np.float32))
    transition = {TransitionKey.OBSERVATION: {OBS_STATE: state}, TransitionKey.COMPLEMENTARY_DATA: {"task": tasks}}
    out = Pi05PrepareStateTokenizerProcessorStep(max_state_dim=32)(transition)
    return list(out[TransitionKey.COMPLEMENTARY_DATA]["task"])


def copy_dir(src: Path, dst: Path, files: list[str], config: dict | None = None) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for f in files:
        shutil.copy(src / f, dst / f)
    if config is not None:
        (dst / "tokenizer_config.json").write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
    return dst


def write_jsonl(path: Path, rows: list[dict]) -> None:
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        for r in rows:
            f.write(json.dumps(r, ensure_ascii=False, separators=(",", ":")) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(REPO / "tests/fixtures/tokenizer/paligemma"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="paligemma_tok_"))
    try:
        hub = work / "hub"
        snapshot = paligemma_tokenizer.write_hub_cache(hub)
        for f in FILES:
            shutil.copy(snapshot / f, out / f)
        # What lerobot runs: the repository id resolved in the hub cache, offline.
        hf = AutoTokenizer.from_pretrained(paligemma_tokenizer.REPO_ID, cache_dir=str(hub))
        assert type(hf).__name__ == "GemmaTokenizer", type(hf)
        model_dir = copy_dir(out, work / "model_only", MODEL_ONLY)
        hf_model = AutoTokenizer.from_pretrained(str(model_dir))
        assert type(hf_model).__name__ == "GemmaTokenizer", type(hf_model)
        sp = spm.SentencePieceProcessor(model_file=str(out / "tokenizer.model"))

        texts = corpus()
        meta = {
            "generator": "tools/oracle/paligemma_tokenizer_fixtures.py",
            "repo_id": paligemma_tokenizer.REPO_ID,
            "transformers": transformers.__version__,
            "tokenizers": tokenizers.__version__,
            "sentencepiece": spm.__version__,
            "python": sys.version.split()[0],
            "class": type(hf).__name__,
            "vocab_size": hf.backend_tokenizer.get_vocab_size(with_added_tokens=True),
            "model_vocab_size": hf_model.backend_tokenizer.get_vocab_size(with_added_tokens=True),
            "padding_side": hf.padding_side,
            "truncation_side": hf.truncation_side,
            "pad_token_id": hf.pad_token_id,
            "bos_token_id": hf.bos_token_id,
            "eos_token_id": hf.eos_token_id,
            "model_padding_side": hf_model.padding_side,
        }
        rows, sp_differs = [], []
        for i, text in enumerate(texts):
            ids = hf(text)["input_ids"]
            plain = hf(text, add_special_tokens=False)["input_ids"]
            model_ids = hf_model(text)["input_ids"]
            model_plain = hf_model(text, add_special_tokens=False)["input_ids"]
            sp_ids = sp.encode(text)
            row = {
                "i": i, "text": text, "ids": ids, "ids_plain": plain, "model_ids": model_ids,
                "model_ids_plain": model_plain,
                "decode": hf.backend_tokenizer.decode(ids, skip_special_tokens=False),
                "decode_skip": hf.backend_tokenizer.decode(ids, skip_special_tokens=True),
                "model_decode_skip": hf_model.backend_tokenizer.decode(model_ids, skip_special_tokens=True),
            }
            if sp_ids != plain:
                row["sentencepiece_ids"] = sp_ids
                sp_differs.append(i)
            rows.append(row)
        meta["strings"] = len(texts)
        meta["sentencepiece_differs"] = len(sp_differs)
        write_jsonl(out / "expected.jsonl", [{"meta": meta}] + rows)

        # Batches as lerobot's TokenizerProcessorStep calls the tokenizer, and other settings.
        rng = random.Random(2468)
        nprng = np.random.default_rng(1357)
        tasks = tf.ROBOT_TASKS + paligemma_tokenizer.CORPUS[:15]
        batch_rows = [{"meta": meta}]

        def record(route, tok, batch, kwargs):
            enc = tok(batch, **kwargs)
            batch_rows.append({
                "route": route, "texts": batch, "padding": kwargs["padding"], "max_length": kwargs["max_length"],
                "truncation": kwargs["truncation"], "padding_side": kwargs.get("padding_side"),
                "add_special_tokens": kwargs.get("add_special_tokens", True),
                "input_ids": enc["input_ids"], "attention_mask": enc["attention_mask"],
            })

        lerobot = dict(padding="max_length", truncation=True, padding_side="right")
        for k in range(10):  # pi0: task + "\n", max_length 48
            batch = [t + "\n" for t in rng.sample(tasks, rng.randint(1, 6))]
            if k == 0:
                batch = ["pick up the red cube and place it in the bowl " * 4 + "\n"]  # longer than 48
            for route, tok in (("json", hf), ("model", hf_model)):
                record(route, tok, batch, dict(lerobot, max_length=48))
        for k in range(8):  # pi0.5: lerobot's prompt step, max_length 200
            batch = pi05_prompts(rng.sample(tasks, rng.randint(1, 5)), nprng)
            for route, tok in (("json", hf), ("model", hf_model)):
                record(route, tok, batch, dict(lerobot, max_length=200))
        others = [
            dict(padding="max_length", max_length=5, truncation=True, padding_side="right"),
            dict(padding="max_length", max_length=1, truncation=True, padding_side="right"),
            dict(padding="max_length", max_length=48, truncation=True, padding_side="left"),
            dict(padding="max_length", max_length=48, truncation=True),  # the class default side
            dict(padding="longest", max_length=48, truncation=True, padding_side="right"),
            dict(padding="longest", max_length=6, truncation=True),
            dict(padding="max_length", max_length=48, truncation=True, padding_side="right", add_special_tokens=False),
        ]
        for kwargs in others:
            batch = rng.sample(texts[:150], 4) + [""]
            for route, tok in (("json", hf), ("model", hf_model)):
                record(route, tok, batch, kwargs)
        write_jsonl(out / "batch.jsonl", batch_rows)

        # Other tokenizer_config.json contents on either route.
        base = json.loads((out / "tokenizer_config.json").read_text())
        no_flags = {k: v for k, v in base.items() if k not in ("add_bos_token", "add_eos_token")}
        no_extra = {k: v for k, v in base.items() if k != "extra_special_tokens"}
        variants = [
            ("model_bos_eos", MODEL_ONLY, dict(base, add_eos_token=True)),
            ("model_eos_only", MODEL_ONLY, dict(base, add_bos_token=False, add_eos_token=True)),
            ("model_no_flags", MODEL_ONLY, no_flags),
            ("model_no_extra", MODEL_ONLY, no_extra),
            ("model_minimal", MODEL_ONLY, {"tokenizer_class": "GemmaTokenizer"}),
            ("json_flags_ignored", FILES, dict(base, add_bos_token=False, add_eos_token=True)),
            ("json_minimal", FILES, {"tokenizer_class": "GemmaTokenizerFast"}),
            ("json_right", FILES, dict(base, padding_side="right", truncation_side="left")),
        ]
        # A tokenizer.json whose stages and BPE options differ from the class's: GemmaTokenizer rebuilds them, so
        # only its vocabulary, merges, added tokens and post-processor count.
        odd = json.loads((out / "tokenizer.json").read_text())
        odd["normalizer"] = {"type": "Lowercase"}
        odd["pre_tokenizer"] = {"type": "Whitespace"}
        odd["decoder"] = {"type": "Metaspace", "replacement": "\u2581", "prepend_scheme": "always", "split": True}
        odd["model"].update(byte_fallback=False, fuse_unk=False, unk_token="<mask>")
        variants.append(("json_class_rebuilds_file", FILES, dict(base), odd))
        sample = [t for t in texts if any(s in t for s in SPECIALS)][:12] + texts[:40]
        variant_rows = [{"meta": meta}]
        for name, files, config, *tokenizer_json in variants:
            d = copy_dir(out, work / name, [f for f in files if f != "tokenizer_config.json"], config)
            if tokenizer_json:
                (d / "tokenizer.json").write_text(json.dumps(tokenizer_json[0], ensure_ascii=False))
            tok = AutoTokenizer.from_pretrained(str(d))
            assert type(tok).__name__ == "GemmaTokenizer", (name, type(tok))
            ids = [tok(t)["input_ids"] for t in sample]
            if tokenizer_json:  # the file on its own would tokenize differently
                raw = tokenizers.Tokenizer.from_str(json.dumps(tokenizer_json[0]))
                assert any(raw.encode(t).ids != x for t, x in zip(sample, ids)), name
            variant_rows.append({
                "name": name, "files": [f for f in files if f != "tokenizer_config.json"],
                **({"tokenizer_json": tokenizer_json[0]} if tokenizer_json else {}),
                "tokenizer_config": config, "texts": sample, "ids": ids,
                "decode_skip": [tok.backend_tokenizer.decode(x, skip_special_tokens=True) for x in ids],
                "padding_side": tok.padding_side, "truncation_side": tok.truncation_side,
                "pad_token_id": tok.pad_token_id, "bos_token_id": tok.bos_token_id, "eos_token_id": tok.eos_token_id,
                "num_special_tokens_to_add": tok.num_special_tokens_to_add(),
            })
        write_jsonl(out / "variants.jsonl", variant_rows)

        # The SentencePiece-style decoders on their own, on token lists no encoding produces (incomplete or
        # invalid byte runs, look-alike byte tokens, characters to strip).
        from tokenizers import decoders

        gemma = decoders.Sequence([decoders.Replace("\u2581", " "), decoders.ByteFallback(), decoders.Fuse()])
        decoder_cases = [
            (gemma, ["\u2581pick", "\u2581up", "<0xE6>", "<0x97>", "<0xA5>", "\u2581x"]),
            (gemma, ["<0xE6>", "<0x97>", "a", "<0xC3>", "<0xA9>"]),
            (gemma, ["<0xFF>", "<0xFE>"]),
            (gemma, ["<0xC3>"]),
            (gemma, ["<0x+A>", "<0xzz>", "<0x4>", "<0x041>", "<0xé>", "<0X41>", "<0x41"]),
            (gemma, ["\u2581\u2581", "\u2581", "a\u2581b"]),
            (gemma, []),
            (decoders.ByteFallback(), ["<0x61>", "<0x62>", "c", "<0xF0>", "<0x9F>"]),
            (decoders.Fuse(), ["a", "", "b c"]),
            (decoders.Replace("a", "bb"), ["banana", "xyz"]),
            (decoders.Strip(" ", 1, 0), ["  a ", " b", "c"]),
            (decoders.Strip("\u2581", 2, 1), ["\u2581\u2581\u2581x\u2581\u2581", "\u2581z", "y\u2581"]),
            (decoders.Sequence([decoders.Replace("\u2581", " "), decoders.ByteFallback(), decoders.Fuse(),
                                decoders.Strip(" ", 1, 0)]), ["\u2581Hello", "\u2581world", "<0x21>"]),
        ]
        decoder_rows = [{"meta": meta}]
        for dec, tokens in decoder_cases:
            decoder_rows.append({"decoder": json.loads(dec.__getstate__()), "tokens": tokens,
                                 "text": dec.decode(tokens)})
        write_jsonl(out / "decoders.jsonl", decoder_rows)
        print(f"wrote {len(texts)} strings ({len(sp_differs)} where SentencePiece itself differs), "
              f"{len(batch_rows) - 1} batches, {len(variant_rows) - 1} config variants under {out}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
