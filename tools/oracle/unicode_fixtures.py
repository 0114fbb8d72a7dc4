#!/usr/bin/env python3
"""Generates the Unicode coverage fixtures for the tokenizer: strings built from code points added in
Unicode 14, 15, 15.1 and 16 (letters, marks, numbers, emoji), combining marks, CJK extension blocks,
Hangul, right-to-left scripts, digits of other scripts, whitespace variants and mixed strings, with the
pre-tokenizer splits and the ids upstream `tokenizers` / `transformers` produce for them.

Usage (inside the oracle venv, after tokenizer_fixtures.py and the SmolVLA fixtures have been written):
    python unicode_fixtures.py [--out tests/fixtures/tokenizer/unicode]
    python unicode_fixtures.py --every-code-point --out DIR   (every scalar value in context; large, not
                                                               committed, for measurements)
Deterministic: regenerating gives the same files.
"""

import argparse
import json
import os
import random
import sys
import unicodedata
from pathlib import Path

os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import tokenizers  # noqa: E402
import transformers  # noqa: E402
from tokenizers import Regex, Tokenizer, pre_tokenizers  # noqa: E402

from tokenizer_fixtures import GPT2_PATTERN, LLAMA3_PATTERN, QWEN2_PATTERN  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
TOKENIZER_FIXTURES = REPO / "tests/fixtures/tokenizer"
SMOLVLA_VLM = REPO / "tests/fixtures/smolvla/cam1_stats/checkpoint/vlm"

# Patterns whose isolated splits are recorded: the three byte-level families' pre-tokenizer
# patterns and the misc fixture's class patterns.
PATTERNS = {
    "gpt2": GPT2_PATTERN,
    "llama3": LLAMA3_PATTERN,
    "qwen2": QWEN2_PATTERN,
    "letters_marks": r"[\p{L}\p{M}]+",
    "word": r"\w+",
    "space": r"\s+",
    "digit": r"\d+",
}

# Tokenizers whose ids are recorded: fixture directory -> loaded the transformers way (a
# tokenizer_config.json is present) or from tokenizer.json alone.
TOKENIZERS = {
    "smollm": TOKENIZER_FIXTURES / "smollm",
    "gpt2": TOKENIZER_FIXTURES / "gpt2",
    "llama3": TOKENIZER_FIXTURES / "llama3",
    "qwen2": TOKENIZER_FIXTURES / "qwen2",
    "misc": TOKENIZER_FIXTURES / "misc",
    "smollm_gpt2cls": TOKENIZER_FIXTURES / "smollm_gpt2cls",
    "smolvla_vlm": SMOLVLA_VLM,
}

# ---------------------------------------------------------------------------------------------
# Code point groups: (name, [(first, last), ...]). Ranges are inclusive; a few code points of each
# are sampled, spread over the range.

GROUPS = [
    # Unicode 14.0
    ("u14_letters", [(0x10570, 0x105BC), (0x1E290, 0x1E2AD), (0x12F90, 0x12FF0), (0x10F70, 0x10F81),
                     (0x16A70, 0x16ABE), (0x10780, 0x107BA), (0x1DF00, 0x1DF1E), (0x0870, 0x0887),
                     (0x1E7E0, 0x1E7FE), (0x1AFF0, 0x1AFFE), (0x1B11F, 0x1B122), (0x0C5D, 0x0C5D)]),
    ("u14_marks", [(0x10F82, 0x10F85), (0x0898, 0x089F), (0x1CF00, 0x1CF2D), (0x1CF30, 0x1CF46),
                   (0x0C3C, 0x0C3C), (0x180F, 0x180F), (0x1E2AE, 0x1E2AE)]),
    ("u14_numbers", [(0x16AC0, 0x16AC9), (0x1E2F0, 0x1E2F9)]),
    ("u14_emoji", [(0x1FAE0, 0x1FAE7), (0x1FAF0, 0x1FAF6), (0x1F6DD, 0x1F6DF), (0x1F7F0, 0x1F7F0),
                   (0x1FA7B, 0x1FA7C), (0x1FAA9, 0x1FAAC), (0x1FAB7, 0x1FABA), (0x1FAC3, 0x1FAC5),
                   (0x1FAD7, 0x1FAD9)]),
    # Unicode 15.0
    ("u15_letters", [(0x11F04, 0x11F10), (0x11F12, 0x11F33), (0x1E4D0, 0x1E4EB), (0x1E030, 0x1E06D),
                     (0x1DF25, 0x1DF2A), (0x31350, 0x323AF), (0x1123F, 0x11240), (0x1B132, 0x1B132),
                     (0x1B155, 0x1B155)]),
    ("u15_marks", [(0x11F00, 0x11F03), (0x11F34, 0x11F3A), (0x1E4EC, 0x1E4EF), (0x10EFD, 0x10EFF),
                   (0x0CF3, 0x0CF3), (0x0ECE, 0x0ECE), (0x11241, 0x11241), (0x1E08F, 0x1E08F)]),
    ("u15_numbers", [(0x11F50, 0x11F59), (0x1E4F0, 0x1E4F9), (0x1D2C0, 0x1D2D3)]),
    ("u15_emoji", [(0x1FA75, 0x1FA77), (0x1F6DC, 0x1F6DC), (0x1FA87, 0x1FA88), (0x1FAAD, 0x1FAAF),
                   (0x1FABB, 0x1FABD), (0x1FABF, 0x1FABF), (0x1FACE, 0x1FACF), (0x1FADA, 0x1FADB),
                   (0x1FAE8, 0x1FAE8), (0x1FAF7, 0x1FAF8)]),
    ("u15_other", [(0x11B00, 0x11B09), (0x11F3E, 0x11F4F)]),
    # Unicode 15.1
    ("u15_1_letters", [(0x2EBF0, 0x2EE5D)]),
    ("u15_1_symbols", [(0x2FFC, 0x2FFF), (0x31EF, 0x31EF)]),
    # Unicode 16.0
    ("u16_letters", [(0x105C0, 0x105F3), (0x10D4A, 0x10D4D), (0x10D50, 0x10D65), (0x10D70, 0x10D85),
                     (0x16100, 0x1611D), (0x16D40, 0x16D6C), (0x1E5D0, 0x1E5ED), (0x1E5F0, 0x1E5F0),
                     (0x11BC0, 0x11BE0), (0x11380, 0x11389), (0x113B7, 0x113B7), (0x13460, 0x143FA),
                     (0xA7CB, 0xA7CD), (0xA7DA, 0xA7DC), (0x1C89, 0x1C8A), (0x10EC2, 0x10EC4)]),
    ("u16_marks", [(0x10D69, 0x10D6D), (0x1611E, 0x1612F), (0x1E5EE, 0x1E5EF), (0x113B8, 0x113C0),
                   (0x113CC, 0x113D0), (0x11F5A, 0x11F5A), (0x0897, 0x0897), (0x1E4EF, 0x1E4EF)]),
    ("u16_numbers", [(0x10D40, 0x10D49), (0x16130, 0x16139), (0x16D70, 0x16D79), (0x1E5F1, 0x1E5FA),
                     (0x11BF0, 0x11BF9), (0x116D0, 0x116E3), (0x1CCF0, 0x1CCF9), (0x11DE0, 0x11DE9)]),
    ("u16_emoji", [(0x1FAE9, 0x1FAE9), (0x1FAC6, 0x1FAC6), (0x1FABE, 0x1FABE), (0x1FADF, 0x1FADF),
                   (0x1FA89, 0x1FA89), (0x1FA8F, 0x1FA8F), (0x1F8B2, 0x1F8BB), (0x1F8C0, 0x1F8C1)]),
    ("u16_symbols", [(0x1CC00, 0x1CCEF), (0x1CD00, 0x1CEB3), (0x2427, 0x2429), (0x31E4, 0x31E5)]),
    # Unassigned in Unicode 16.0, private use, noncharacters
    ("unassigned", [(0x0378, 0x0379), (0x1FAFA, 0x1FAFF), (0x2EE5E, 0x2EE6F), (0x3FFFD, 0x3FFFD),
                    (0xE0080, 0xE0080), (0x10FFFE, 0x10FFFF), (0xFDD0, 0xFDD3)]),
    ("private_use", [(0xE000, 0xE003), (0xF8FF, 0xF8FF), (0xF0000, 0xF0002), (0x100000, 0x100001)]),
    # Combining marks
    ("combining", [(0x0300, 0x036F), (0x0483, 0x0489), (0x0591, 0x05BD), (0x064B, 0x065F),
                   (0x0900, 0x0903), (0x093C, 0x094F), (0x1AB0, 0x1ACE), (0x1DC0, 0x1DFF),
                   (0x20D0, 0x20F0), (0xFE00, 0xFE0F), (0xFE20, 0xFE2F), (0xE0100, 0xE01EF),
                   (0x1D165, 0x1D169), (0x0E31, 0x0E31), (0x0E34, 0x0E3A), (0x302A, 0x302F),
                   (0x3099, 0x309A)]),
    # CJK: unified blocks and their extensions, compatibility ideographs, radicals
    ("cjk", [(0x4E00, 0x9FFF), (0x3400, 0x4DBF), (0x20000, 0x2A6DF), (0x2A700, 0x2B739),
             (0x2B740, 0x2B81D), (0x2B820, 0x2CEA1), (0x2CEB0, 0x2EBE0), (0x30000, 0x3134A),
             (0xF900, 0xFAD9), (0x2F800, 0x2FA1D), (0x2E80, 0x2EF3), (0x2F00, 0x2FD5), (0x3005, 0x3007),
             (0x3021, 0x3029), (0x3038, 0x303B), (0x3041, 0x3096), (0x30A1, 0x30FA), (0xFF66, 0xFF9D)]),
    # Hangul: syllables, conjoining jamo (with the fillers), compatibility and halfwidth jamo
    ("hangul", [(0xAC00, 0xD7A3), (0x1100, 0x11FF), (0xA960, 0xA97C), (0xD7B0, 0xD7FB),
                (0x3131, 0x318E), (0xFFA0, 0xFFDC), (0x3164, 0x3164), (0x115F, 0x1160)]),
    # Right-to-left scripts, their digits and the direction controls
    ("rtl", [(0x05D0, 0x05EA), (0x0620, 0x064A), (0x0671, 0x06D3), (0x0640, 0x0640), (0x0710, 0x072F),
             (0x0780, 0x07A5), (0x07CA, 0x07EA), (0x0800, 0x0815), (0x0840, 0x0858), (0x1E900, 0x1E943),
             (0x10D00, 0x10D23), (0x10E80, 0x10EA9), (0xFB50, 0xFBB1), (0xFE70, 0xFEFC),
             (0x10800, 0x10805), (0x10900, 0x10915), (0x10A00, 0x10A00), (0x10B00, 0x10B35)]),
    ("bidi_controls", [(0x200E, 0x200F), (0x202A, 0x202E), (0x2066, 0x2069), (0x061C, 0x061C)]),
    # Digits and numbers of other scripts (Nd, Nl, No)
    ("digits", [(0x0660, 0x0669), (0x06F0, 0x06F9), (0x07C0, 0x07C9), (0x0966, 0x096F), (0x09E6, 0x09EF),
                (0x0A66, 0x0A6F), (0x0BE6, 0x0BF2), (0x0E50, 0x0E59), (0x0ED0, 0x0ED9), (0x0F20, 0x0F33),
                (0x1040, 0x1049), (0x17E0, 0x17E9), (0x1810, 0x1819), (0x1946, 0x194F), (0xA8D0, 0xA8D9),
                (0xFF10, 0xFF19), (0x104A0, 0x104A9), (0x1D7CE, 0x1D7FF), (0x1E950, 0x1E959),
                (0x10D30, 0x10D39), (0x1FBF0, 0x1FBF9), (0x16E80, 0x16E96)]),
    ("numbers_other", [(0x2160, 0x2188), (0x2460, 0x249B), (0x2070, 0x2079), (0x2080, 0x2089),
                       (0x00BC, 0x00BE), (0x2150, 0x215F), (0x3007, 0x3007), (0x3021, 0x3029),
                       (0x3192, 0x3195), (0x3220, 0x3229), (0x10107, 0x10133), (0x1D360, 0x1D378),
                       (0x12400, 0x1246E), (0x1F100, 0x1F10C), (0x0F2A, 0x0F33), (0x1372, 0x137C)]),
    # Whitespace variants and look-alikes that are not White_Space
    ("whitespace", [(0x0009, 0x000D), (0x0020, 0x0020), (0x0085, 0x0085), (0x00A0, 0x00A0),
                    (0x1680, 0x1680), (0x2000, 0x200A), (0x2028, 0x2029), (0x202F, 0x202F),
                    (0x205F, 0x205F), (0x3000, 0x3000)]),
    ("not_whitespace", [(0x180E, 0x180E), (0x200B, 0x200D), (0x2060, 0x2064), (0xFEFF, 0xFEFF),
                        (0x001C, 0x001F), (0x115F, 0x115F), (0x3164, 0x3164), (0x2800, 0x2800),
                        (0x034F, 0x034F), (0x00AD, 0x00AD)]),
]

# Emoji sequences (ZWJ, modifiers, flags, keycaps, tags), including the Emoji 15.1 and 16.0 ones
EMOJI_SEQUENCES = [
    "\U0001F642\u200D\u2194\uFE0F", "\U0001F642\u200D\u2195\uFE0F", "\U0001F426\u200D\U0001F525",
    "\U0001F34B\u200D\U0001F7E9", "\U0001F344\u200D\U0001F7EB", "\u26D3\uFE0F\u200D\U0001F4A5",
    "\U0001F9D1\u200D\U0001F9D1\u200D\U0001F9D2", "\U0001F6B6\u200D\u27A1\uFE0F",
    "\U0001F3C3\U0001F3FD\u200D\u2640\uFE0F\u200D\u27A1\uFE0F", "\U0001F1E8\U0001F1F6",
    "\U0001F3F4\U000E0067\U000E0062\U000E0073\U000E0063\U000E0074\U000E007F", "1\uFE0F\u20E3",
    "\U0001FAF1\U0001F3FB\u200D\U0001FAF2\U0001F3FF", "\U0001FAE8", "\U0001FA75\U0001FA76\U0001FA77",
    "\U0001F469\U0001F3FE\u200D\U0001F9BD\u200D\u27A1\uFE0F", "\U0001FAE9\U0001FAC6\U0001FABE",
]

WORDS = ["pick", "up", "the", "cube", "Robot", "arm", "left", "x", "a", "OK", "it's", "I'm"]
SEPARATORS = ["", " ", "  ", "\n", "\t", " \n", "\u00a0", "\u3000", "-", ".", ",", "'s", "1", "12"]


def group_version(name):
    """The Unicode version a group's code points were added in ("15.1" for u15_1_*), or None."""
    for prefix, version in (("u15_1_", "15.1"), ("u14_", "14.0"), ("u15_", "15.0"), ("u16_", "16.0")):
        if name.startswith(prefix):
            return version
    return None


VERSION_OF = {}  # code point -> the Unicode version it was added in, for the versioned groups
for _name, _ranges in GROUPS:
    if group_version(_name):
        for _a, _b in _ranges:
            for _p in range(_a, _b + 1):
                VERSION_OF[_p] = group_version(_name)


def newest_version(text):
    versions = [VERSION_OF[ord(c)] for c in text if ord(c) in VERSION_OF]
    return max(versions, key=lambda v: tuple(map(int, v.split(".")))) if versions else None


def sample(ranges, k):
    """Up to k code points spread evenly over the ranges (first and last included), surrogates skipped."""
    points = []
    total = sum(b - a + 1 for a, b in ranges)
    if total <= k:
        for a, b in ranges:
            points.extend(range(a, b + 1))
    else:
        flat_index = [round(i * (total - 1) / (k - 1)) for i in range(k)]
        for idx in flat_index:
            for a, b in ranges:
                if idx < b - a + 1:
                    points.append(a + idx)
                    break
                idx -= b - a + 1
        for a, b in ranges:  # every range is represented by its first code point
            if a not in points:
                points.append(a)
    return [p for p in dict.fromkeys(points) if not 0xD800 <= p <= 0xDFFF]


def contexts(c):
    """The character alone, in a word, after a space, repeated, between digits, after a quote."""
    return [c, f"a{c}b", f" {c}", f"{c}{c}{c}", f"1{c}2", f"x {c}{c} y", f"'{c}", f"{c}'s", f"\n{c}\n"]


def curated_cases():
    rng = random.Random(20240616)
    cases = []
    pools = {}
    for name, ranges in GROUPS:
        pts = sample(ranges, 24)
        pools[name] = [chr(p) for p in pts]
        for i, p in enumerate(pts):
            ctx = contexts(chr(p))
            # every code point alone and in a word; the other contexts in rotation
            cases.append(ctx[0])
            cases.append(ctx[1])
            cases.append(ctx[2 + i % (len(ctx) - 2)])
        # a run of the group's characters, and the run after a space
        run = "".join(chr(p) for p in pts[:12])
        cases.extend([run, " " + run, run + " " + run])
    for seq in EMOJI_SEQUENCES:
        cases.extend([seq, f"a{seq}b", f" {seq} {seq}", f"{seq}1"])
    # Combining marks stacked on letters of several scripts, and on spaces and digits
    marks = pools["combining"]
    for base in ["a", "Z", "\u05d0", "\u0627", "\u0915", "\u4e00", "\uac00", " ", "1", "\U00010570",
                 "\U0002EBF0", "\U000105C0"]:
        cases.append(base + "".join(rng.sample(marks, 3)))
        cases.append("x" + base + rng.choice(marks) + "y")
    # Mixed strings: words, separators and characters from several groups
    names = list(pools)
    for _ in range(600):
        parts = []
        for _ in range(rng.randint(2, 7)):
            r = rng.random()
            if r < 0.3:
                parts.append(rng.choice(WORDS))
            elif r < 0.4:
                parts.append(rng.choice(EMOJI_SEQUENCES))
            else:
                group = pools[rng.choice(names)]
                parts.append("".join(rng.choice(group) for _ in range(rng.randint(1, 4))))
            parts.append(rng.choice(SEPARATORS))
        s = "".join(parts)
        if rng.random() < 0.3:
            s += "\n"
        if rng.random() < 0.1:
            s = unicodedata.normalize("NFD", s)
        cases.append(s)
    return list(dict.fromkeys(cases))


def every_code_point_cases():
    """Each scalar value in one string that exercises letter, number, space and prefix handling."""
    out = []
    for p in range(0x110000):
        if 0xD800 <= p <= 0xDFFF:
            continue
        c = chr(p)
        out.append(f"a{c}b {c}{c}1 {c}")
    return out


# ---------------------------------------------------------------------------------------------


def splitters():
    return {name: pre_tokenizers.Split(Regex(p), behavior="isolated", invert=False) for name, p in PATTERNS.items()}


def encoders():
    out = {}
    for name, d in TOKENIZERS.items():
        if (d / "tokenizer_config.json").exists():
            hf = transformers.AutoTokenizer.from_pretrained(str(d))
            out[name] = (lambda t, hf=hf: hf(t, add_special_tokens=False)["input_ids"],
                         lambda ts, hf=hf: hf(ts, add_special_tokens=False)["input_ids"])
        else:
            tok = Tokenizer.from_file(str(d / "tokenizer.json"))
            out[name] = (lambda t, tok=tok: tok.encode(t, add_special_tokens=False).ids,
                         lambda ts, tok=tok: [e.ids for e in tok.encode_batch(ts, add_special_tokens=False)])
    return out


def write_jsonl(path, rows):
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        for r in rows:
            f.write(json.dumps(r, ensure_ascii=False, separators=(",", ":")) + "\n")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(TOKENIZER_FIXTURES / "unicode"))
    ap.add_argument("--every-code-point", action="store_true")
    ap.add_argument("--cases", help="take the strings from this cases.jsonl instead (measurements)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    if args.cases:
        with open(args.cases, encoding="utf-8") as f:
            cases = [r["text"] for r in map(json.loads, f) if "text" in r]
    else:
        cases = every_code_point_cases() if args.every_code_point else curated_cases()
    meta = {
        "generator": "tools/oracle/unicode_fixtures.py" + (" --every-code-point" if args.every_code_point else ""),
        "tokenizers": tokenizers.__version__, "transformers": transformers.__version__,
        "python": sys.version.split()[0], "python_unicode": unicodedata.unidata_version, "patterns": PATTERNS, "tokenizers_dirs": {
            k: str(v.relative_to(REPO)) for k, v in TOKENIZERS.items()},
    }
    split = splitters()
    enc = encoders()
    if args.every_code_point:  # the byte-level families only, to keep the file within bounds
        split = {k: v for k, v in split.items() if k in ("gpt2", "llama3", "qwen2")}
        enc = {k: v for k, v in enc.items() if k in ("smollm", "llama3", "qwen2", "smolvla_vlm")}
    ids = {name: batch(cases) for name, (_, batch) in enc.items()}
    rows = [{"meta": meta}]
    for i, text in enumerate(cases):
        version = newest_version(text)
        rows.append({
            "i": i, "text": text, **({"unicode": version} if version else {}),
            "splits": {name: [piece for piece, _ in sp.pre_tokenize_str(text)] for name, sp in split.items()},
            "ids": {name: ids[name][i] for name in enc},
        })
    write_jsonl(out / "expected.jsonl", rows)
    size = (out / "expected.jsonl").stat().st_size
    print(f"wrote {len(cases)} strings, {len(PATTERNS)} patterns, {len(enc)} tokenizers, {size / 1e6:.2f} MB under {out}")


if __name__ == "__main__":
    main()
