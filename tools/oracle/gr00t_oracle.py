"""Writes GR00T N1.7 checkpoints in NVIDIA's raw on-disk layout and runs lerobot's N1.7 code on them.

Sub-commands:
  hub       [--out DIR] [--full-out DIR] [--tiny-only]
                      stand-in backbone repositories as Hugging Face hub caches: the tiny Qwen3-VL
                      `tether-fixtures/cosmos-reason2-tiny` (tests/fixtures/gr00t_hub) and, unless --tiny-only,
                      `nvidia/Cosmos-Reason2-2B` with the real sizes and token ids
                      (${TETHER_CACHE:-~/.cache/tether}/gr00t_hub, not committed)
  fixtures  [--out DIR] [--cases a,b]
                      tiny N1.7 checkpoints + oracle.safetensors per case (tests/fixtures/gr00t_n17)
  full-size [--out DIR] [--check-only] [--load]
                      random-weight checkpoint with the real N1.7 sizes in bfloat16 shards (benchmarks, not
                      committed); --load also loads it with GR00TN17.from_pretrained

Nothing is downloaded. lerobot's N1.7 network builds its backbone from `config.model_name`: the hard-coded
Cosmos-Reason2-2B config for that exact id, `AutoConfig.from_pretrained(model_name)` for any other id. The tiny
fixtures name `tether-fixtures/cosmos-reason2-tiny`, a repository that exists only in the stand-in hub cache this
script writes (HF_HUB_CACHE points there, set below before any Hugging Face import; override with
TETHER_GR00T_HUB). Its tokenizer is a byte-level BPE trained here in Qwen2's shape with the Qwen3-VL special tokens
appended, its chat template renders Qwen3-VL's instruct format, and its image processor files are Qwen3-VL's with
a smaller minimum pixel count (fixture size).

lerobot's pre-processor hard-codes the backbone id "nvidia/Cosmos-Reason2-2B" for its Qwen3-VL processor; for the
tiny fixtures the one attribute `GrootN17VLMEncodeStep.model_name` is set to the tiny id before the step is first
used. The flow-matching noise is drawn inside upstream's sampler with `torch.randn`; the oracle replaces
`torch.randn` only for the duration of that one call and hands back a seeded tensor. Both are recorded in each
fixture's metadata.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("TETHER_CACHE", Path.home() / ".cache" / "tether"))
HUB_CACHE = Path(os.environ.get("TETHER_GR00T_HUB", REPO_ROOT / "tests" / "fixtures" / "gr00t_hub"))
FULL_HUB_CACHE = CACHE / "gr00t_hub"
if __name__ == "__main__":
    # the full-size command reads the stand-in under the real id; everything else the committed tiny cache
    _hub = FULL_HUB_CACHE if len(sys.argv) > 1 and sys.argv[1] == "full-size" else HUB_CACHE
    os.environ["HF_HUB_CACHE"] = str(os.environ.get("TETHER_GR00T_HUB", _hub))

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402
from smolvla_oracle import write_safetensors  # noqa: E402
from tokenizers import (  # noqa: E402
    AddedToken,
    Regex,
    Tokenizer,
    decoders,
    models,
    normalizers,
    pre_tokenizers,
    processors,
    trainers,
)

CHAT_TEMPLATE = (
    "{%- for message in messages -%}"
    "{{- '<|im_start|>' + message['role'] + '\\n' -}}"
    "{%- if message['content'] is string -%}"
    "{{- message['content'] -}}"
    "{%- else -%}"
    "{%- for item in message['content'] -%}"
    "{%- if item['type'] == 'image' or 'image' in item or 'image_url' in item -%}"
    "{{- '<|vision_start|><|image_pad|><|vision_end|>' -}}"
    "{%- elif item['type'] == 'video' or 'video' in item -%}"
    "{{- '<|vision_start|><|video_pad|><|vision_end|>' -}}"
    "{%- elif 'text' in item -%}"
    "{{- item['text'] -}}"
    "{%- endif -%}"
    "{%- endfor -%}"
    "{%- endif -%}"
    "{{- '<|im_end|>\\n' -}}"
    "{%- endfor -%}"
    "{%- if add_generation_prompt -%}"
    "{{- '<|im_start|>assistant\\n' -}}"
    "{%- endif -%}"
)

# ----------------------------------------------------------------------------------------------
# Stand-in backbone repositories (tokenizer, processor files, Qwen3-VL config)

TINY_REPO = "tether-fixtures/cosmos-reason2-tiny"
FULL_REPO = "nvidia/Cosmos-Reason2-2B"
# made-up revisions: the hub cache layout needs one (refs/main names it)
TINY_REVISION = "5d1c0e2b7a4f49388c6e1b0d2f7a9c3e4b5d6f70"
FULL_REVISION = "9b2e4c6a8d0f1e3b5c7d9f1a3c5e7b9d1f3a5c7e"

# Qwen2's pre-tokenizer split pattern (the same text as transformers' Qwen2Tokenizer and Qwen's tokenizer.json)
QWEN2_SPLIT = (
    r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+"
)

# Qwen3-VL's added tokens in id order (they follow the 151643-entry base vocabulary in the real tokenizer);
# the flag says whether the token is special (the last twelve are not).
QWEN3_VL_ADDED = [
    ("<|endoftext|>", True),
    ("<|im_start|>", True),
    ("<|im_end|>", True),
    ("<|object_ref_start|>", True),
    ("<|object_ref_end|>", True),
    ("<|box_start|>", True),
    ("<|box_end|>", True),
    ("<|quad_start|>", True),
    ("<|quad_end|>", True),
    ("<|vision_start|>", True),
    ("<|vision_end|>", True),
    ("<|vision_pad|>", True),
    ("<|image_pad|>", True),
    ("<|video_pad|>", True),
    ("<tool_call>", False),
    ("</tool_call>", False),
    ("<|fim_prefix|>", False),
    ("<|fim_middle|>", False),
    ("<|fim_suffix|>", False),
    ("<|fim_pad|>", False),
    ("<|repo_name|>", False),
    ("<|file_sep|>", False),
    ("<tool_response>", False),
    ("</tool_response>", False),
    ("<think>", False),
    ("</think>", False),
]
REAL_BASE_VOCAB = 151643  # id of <|endoftext|> in Qwen2 / Qwen3 tokenizers
TINY_BASE_VOCAB = 512  # 256 byte symbols + 256 merges
TINY_VOCAB_SIZE = 576  # embedding rows (the real model pads 151669 tokens to 151936)

CORPUS = [
    "pick up the red cube and place it in the bowl",
    "Pick up the blue block, then put it on the plate.",
    "open the top drawer and put the black bowl inside",
    "stack the green cube on top of the yellow one",
    "move the arm to the left; grasp the handle (gently!)",
    "Place the 2 blue blocks, then stack 3 more on the tray",
    "push the button 10 times: then wait 5 seconds",
    "put the sponge in the sink and turn on the water",
    "fold the towel in half twice and place it on the shelf",
    "rotate the knob by 90 degrees counter-clockwise",
    "Insert the peg into the hole, then release the gripper.",
    "grab the cup by its handle and pour the water into the pot",
    "the robot should pick the object closest to the camera",
    "wipe the table with the cloth, starting from the corner",
    "Sort the pieces by color: red, green, blue and yellow.",
    "put both the alphabet soup and the tomato sauce in the basket",
    "turn on the stove and put the moka pot on it",
    "put the white mug on the left plate and put the yellow and white mug on the right plate",
    "pick up the book and place it in the back compartment of the caddy",
    "put the black bowl in the bottom drawer of the cabinet and close it",
    "Perform the task.",
    "perform the task",
    "The quick brown fox jumps over the lazy dog while the robot watches.",
    "A camera looks at the kitchen counter, where a bowl, a cup and a spoon are waiting.",
    "Move slowly towards the target, then close the gripper around the object and lift it up.",
    "When the light turns green, the arm should reach forward and press the large button.",
    "There are three apples and two oranges on the wooden table next to the window.",
    "Please carefully open the cabinet door, take out the plate, and set it down gently.",
    "The gripper is open; the wrist camera shows the handle of the drawer in the middle of the image.",
    "Walk to the door, turn the handle, pull it open and step through without touching the frame.",
    "I'm sure it's the one we've seen before, they'll say it'd be fine.",
    "Water the plants in the garden every morning before the sun gets too hot.",
    "Count the boxes: 12 red, 7 blue, 30 green and 4 yellow ones.",
    "Hold the bottle upright, unscrew the cap and pour half of the water into the glass.",
    "Slide the tray under the shelf and push it all the way to the back wall.",
    "Look at the screen, read the number and type it into the keypad on the right.",
]


def qwen2_pipeline(tok: Tokenizer) -> None:
    """Qwen2's normaliser, pre-tokenizer, post-processor and decoder (as its tokenizer.json has them)."""
    tok.normalizer = normalizers.NFC()
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(QWEN2_SPLIT), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, trim_offsets=False, use_regex=False),
        ]
    )
    tok.post_processor = processors.ByteLevel(add_prefix_space=False, trim_offsets=False, use_regex=False)
    tok.decoder = decoders.ByteLevel(add_prefix_space=False, trim_offsets=False, use_regex=False)


def train_tokenizer(base_vocab: int, fill_to: int | None = None) -> Tokenizer:
    """Byte-level BPE with `base_vocab` entries (256 byte symbols + merges) trained on CORPUS in Qwen2's shape,
    followed directly by Qwen3-VL's added tokens. `fill_to` pads the base vocabulary with entries no merge
    produces, so that the added tokens land at the real Qwen ids."""
    tok = Tokenizer(
        models.BPE(
            unk_token=None,
            continuing_subword_prefix="",
            end_of_word_suffix="",
            fuse_unk=False,
            byte_fallback=False,
            ignore_merges=False,
        )
    )
    qwen2_pipeline(tok)
    trainer = trainers.BpeTrainer(
        vocab_size=base_vocab,
        min_frequency=1,
        show_progress=False,
        special_tokens=[],
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
    )
    tok.train_from_iterator(CORPUS * 4, trainer=trainer)
    if tok.get_vocab_size() != base_vocab:
        raise RuntimeError(f"BPE training gave {tok.get_vocab_size()} entries, wanted {base_vocab}")
    data = json.loads(tok.to_str())
    if fill_to is not None:
        vocab = data["model"]["vocab"]
        while len(vocab) < fill_to:
            vocab[f"<|unused_{len(vocab)}|>"] = len(vocab)
    tok = Tokenizer.from_str(json.dumps(data))
    qwen2_pipeline(tok)
    first = tok.get_vocab_size()
    for i, (content, special) in enumerate(QWEN3_VL_ADDED):
        added = AddedToken(content, special=special, normalized=False, lstrip=False, rstrip=False, single_word=False)
        if special:
            tok.add_special_tokens([added])
        else:
            tok.add_tokens([added])
        if tok.token_to_id(content) != first + i:
            raise RuntimeError(f"{content} got id {tok.token_to_id(content)}, wanted {first + i}")
    return tok


def special_ids(tok: Tokenizer) -> dict[str, int]:
    return {content: tok.token_to_id(content) for content, _ in QWEN3_VL_ADDED}


def tokenizer_config(tok: Tokenizer) -> dict:
    """tokenizer_config.json in the shape of Qwen3-VL's (Qwen2Tokenizer, no bos, <|im_end|> ends a turn)."""
    added = {}
    for content, special in QWEN3_VL_ADDED:
        added[str(tok.token_to_id(content))] = {
            "content": content,
            "lstrip": False,
            "normalized": False,
            "rstrip": False,
            "single_word": False,
            "special": special,
        }
    return {
        "add_bos_token": False,
        "add_prefix_space": False,
        "added_tokens_decoder": added,
        "additional_special_tokens": [c for c, special in QWEN3_VL_ADDED if special and c != "<|endoftext|>"],
        "bos_token": None,
        "chat_template": CHAT_TEMPLATE,
        "clean_up_tokenization_spaces": False,
        "eos_token": "<|im_end|>",
        "errors": "replace",
        "model_max_length": 262144,
        "pad_token": "<|endoftext|>",
        "padding_side": "left",
        "split_special_tokens": False,
        "tokenizer_class": "Qwen2Tokenizer",
        "unk_token": None,
    }


def image_processor_config(min_pixels: int, max_pixels: int) -> dict:
    return {
        "do_convert_rgb": True,
        "do_normalize": True,
        "do_rescale": True,
        "do_resize": True,
        "image_mean": [0.5, 0.5, 0.5],
        "image_processor_type": "Qwen2VLImageProcessor",
        "image_std": [0.5, 0.5, 0.5],
        "merge_size": 2,
        "patch_size": 16,
        "processor_class": "Qwen3VLProcessor",
        "resample": 3,
        "rescale_factor": 1 / 255,
        "size": {"longest_edge": max_pixels, "shortest_edge": min_pixels},
        "temporal_patch_size": 2,
    }


def video_processor_config() -> dict:
    """Qwen3-VL's video processor settings (unused by GR00T: it sends camera frames as images)."""
    return {
        "do_convert_rgb": True,
        "do_normalize": True,
        "do_rescale": True,
        "do_resize": True,
        "do_sample_frames": True,
        "fps": 2,
        "image_mean": [0.5, 0.5, 0.5],
        "image_std": [0.5, 0.5, 0.5],
        "max_frames": 768,
        "merge_size": 2,
        "min_frames": 4,
        "patch_size": 16,
        "processor_class": "Qwen3VLProcessor",
        "resample": 3,
        "rescale_factor": 1 / 255,
        "size": {"longest_edge": 25165824, "shortest_edge": 4096},
        "temporal_patch_size": 2,
        "video_processor_type": "Qwen3VLVideoProcessor",
    }


def qwen3_vl_config_json(*, ids: dict[str, int], vocab_size: int, text: dict, vision: dict) -> dict:
    """A Qwen3-VL config.json in the layout the released repositories use (rope_scaling + rope_theta in
    text_config, as transformers 4.57 writes it); transformers 5 converts it to rope_parameters on load."""
    return {
        "architectures": ["Qwen3VLForConditionalGeneration"],
        "image_token_id": ids["<|image_pad|>"],
        "model_type": "qwen3_vl",
        "text_config": {
            "attention_bias": False,
            "attention_dropout": 0.0,
            "bos_token_id": ids["<|endoftext|>"],
            "dtype": "bfloat16",
            "eos_token_id": ids["<|im_end|>"],
            "hidden_act": "silu",
            "initializer_range": 0.02,
            "max_position_embeddings": 262144,
            "model_type": "qwen3_vl_text",
            "tie_word_embeddings": True,
            "use_cache": True,
            "vocab_size": vocab_size,
            **text,
        },
        "tie_word_embeddings": True,
        # a 4.57 writer, as the released files have (transformers 5 also uses this field to rule out its
        # Mistral pre-tokenizer regex warning)
        "transformers_version": "4.57.1",
        "video_token_id": ids["<|video_pad|>"],
        "vision_config": {
            "hidden_act": "gelu_pytorch_tanh",
            "in_channels": 3,
            "initializer_range": 0.02,
            "model_type": "qwen3_vl",
            "patch_size": 16,
            "spatial_merge_size": 2,
            "temporal_patch_size": 2,
            **vision,
        },
        "vision_end_token_id": ids["<|vision_end|>"],
        "vision_start_token_id": ids["<|vision_start|>"],
    }


TINY_TEXT = {
    "head_dim": 16,
    "hidden_size": 64,
    "intermediate_size": 128,
    "num_attention_heads": 4,
    "num_hidden_layers": 6,
    "num_key_value_heads": 2,
    "rms_norm_eps": 1e-6,
    "rope_scaling": {"mrope_interleaved": True, "mrope_section": [4, 2, 2], "rope_type": "default"},
    "rope_theta": 5000000,
}
TINY_VISION = {
    "deepstack_visual_indexes": [1, 2, 3],
    "depth": 4,
    "hidden_size": 32,
    "intermediate_size": 64,
    "num_heads": 2,
    "num_position_embeddings": 256,
    "out_hidden_size": 64,
}
# the real sizes: the numbers of lerobot's _cosmos_reason2_qwen3_vl_config()
FULL_TEXT = {
    "head_dim": 128,
    "hidden_size": 2048,
    "intermediate_size": 6144,
    "num_attention_heads": 16,
    "num_hidden_layers": 28,
    "num_key_value_heads": 8,
    "rms_norm_eps": 1e-6,
    "rope_scaling": {"mrope_interleaved": True, "mrope_section": [24, 20, 20], "rope_type": "default"},
    "rope_theta": 5000000,
}
FULL_VISION = {
    "deepstack_visual_indexes": [5, 11, 17],
    "depth": 24,
    "hidden_size": 1024,
    "intermediate_size": 4096,
    "num_heads": 16,
    "num_position_embeddings": 2304,
    "out_hidden_size": 2048,
}
# The tiny fixtures resize every camera frame to a shorter side of 64 (GR00T's shortest_image_edge); the
# Qwen3-VL minimum of 65536 pixels would blow each frame up to at least 256x256 (1.5 MB of pixel_values).
# 6144 = 64 x 96 keeps square frames on the upscaling branch of smart_resize and lets 3:4 frames through
# unchanged. The full-size stand-in keeps Qwen3-VL's values.
TINY_MIN_PIXELS = 6144
QWEN3_VL_MIN_PIXELS = 65536
QWEN3_VL_MAX_PIXELS = 16777216

HUB_README = """# Stand-in Qwen3-VL backbone repository (hub cache)

A Hugging Face hub cache holding one repository, `{repo}`, at the made-up revision `{rev}`. It does not
exist on the hub: GR00T N1.7's tiny test checkpoints (`../gr00t_n17`) name it as their `model_name`, so
lerobot builds their Qwen3-VL backbone from its `config.json` (`AutoConfig`) and the oracle's Qwen3-VL
processor from its tokenizer and image processor files (lerobot's pre-processor names the real backbone
`nvidia/Cosmos-Reason2-2B`, a gated repository; the oracle points that step at this id instead).

- `config.json`: a tiny `Qwen3VLConfig` (text: hidden 64, 6 layers of which GR00T keeps 4, 4 heads, 2 KV heads,
  head_dim 16, MLP 128, rope_theta 5000000, interleaved M-RoPE sections [4, 2, 2]; vision: depth 4, hidden 32,
  2 heads, MLP 64, patch 16, temporal patch 2, merge 2, a 16x16 position table, output 64, deep-stack after blocks
  1, 2, 3; vocabulary {vocab_size}), in the layout the released Qwen3-VL repositories use.
- `tokenizer.json`: a byte-level BPE with {base} entries (256 byte symbols + 256 merges trained by
  `tools/oracle/gr00t_oracle.py` on English instructions) in Qwen2's shape: NFC normaliser, Split on Qwen2's
  pattern then ByteLevel without its own regex, ByteLevel post-processor and decoder. Qwen3-VL's 26 added tokens
  follow the vocabulary directly: {ids}.
- `tokenizer_config.json`: `Qwen2Tokenizer`, no bos, eos `<|im_end|>`, pad `<|endoftext|>`, left padding, and a
  chat template that renders Qwen3-VL's instruct format (no default system message; images then text in a user
  turn become `<|im_start|>user\\n` + `<|vision_start|><|image_pad|><|vision_end|>` per image + text +
  `<|im_end|>\\n`; `add_generation_prompt` appends `<|im_start|>assistant\\n`).
- `preprocessor_config.json`: Qwen3-VL's `Qwen2VLImageProcessor` settings (patch 16, temporal patch 2, merge 2,
  mean / std 0.5, bicubic) except `size.shortest_edge` (the minimum pixel count) = {min_pixels} instead of 65536, so
  the fixtures' small frames stay small; `video_preprocessor_config.json`: Qwen3-VL's video processor settings
  (unused: GR00T sends camera frames as images).

Regenerate with `tools/oracle/run.sh gr00t_oracle.py hub` (byte-identical for the pinned versions). The same
command writes a stand-in for `nvidia/Cosmos-Reason2-2B` with the real sizes and the real Qwen token ids to
`${{TETHER_CACHE:-~/.cache/tether}}/gr00t_hub` (not committed; its vocabulary is padded to 151643 entries).
"""


def write_repo(hub_cache: Path, repo_id: str, revision: str, files: dict[str, str]) -> Path:
    """Writes `files` as the hub cache holds repo_id at `revision`; returns the snapshot directory."""
    repo = hub_cache / ("models--" + repo_id.replace("/", "--"))
    if repo.exists():
        shutil.rmtree(repo)
    snapshot = repo / "snapshots" / revision
    snapshot.mkdir(parents=True)
    for name, text in files.items():
        (snapshot / name).write_text(text)
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / "main").write_text(revision)
    return snapshot


def dump_json(obj) -> str:
    return json.dumps(obj, indent=2, sort_keys=True) + "\n"


def tokenizer_json(tok: Tokenizer) -> str:
    """tokenizer.json with the fields Qwen's file spells out explicitly (the Python bindings serialise the empty
    subword affixes as null and the ByteLevel decoder with its default flags; neither changes behaviour)."""
    data = json.loads(tok.to_str())
    data["model"]["continuing_subword_prefix"] = ""
    data["model"]["end_of_word_suffix"] = ""
    data["decoder"] = {"type": "ByteLevel", "add_prefix_space": False, "trim_offsets": False, "use_regex": False}
    text = json.dumps(data, indent=2, ensure_ascii=False) + "\n"
    if Tokenizer.from_str(text).encode(CORPUS[1]).ids != tok.encode(CORPUS[1]).ids:
        raise RuntimeError("rewritten tokenizer.json encodes differently")
    return text


def backbone_files(tok: Tokenizer, *, vocab_size: int, text: dict, vision: dict, min_pixels: int) -> dict[str, str]:
    ids = special_ids(tok)
    return {
        "config.json": dump_json(qwen3_vl_config_json(ids=ids, vocab_size=vocab_size, text=text, vision=vision)),
        "tokenizer.json": tokenizer_json(tok),
        "tokenizer_config.json": dump_json(tokenizer_config(tok)),
        "preprocessor_config.json": dump_json(image_processor_config(min_pixels, QWEN3_VL_MAX_PIXELS)),
        "video_preprocessor_config.json": dump_json(video_processor_config()),
    }


TOKENIZER_CHECK_TEXTS = CORPUS + [
    "Pick up the RED mug (the one on the LEFT), then put it 3 cm behind the blue_plate; don't spill the café!",
    "  two  spaces\tand a tab\nand a newline  ",
    "<|im_start|>user\n<|vision_start|><|image_pad|><|image_pad|><|vision_end|>pick up the cube<|im_end|>\n",
    "unicode: naïve café, Ünïcödé, 東京, emoji 🤖, combining e\u0301",
    "<think>x</think> <tool_call>{}</tool_call>",
]


def check_backbone_repo(snapshot: Path, repo_id: str, tok: Tokenizer, *, vocab_size: int, text: dict) -> None:
    """The repository loads through the Auto* classes lerobot uses and gives the same ids as the raw
    tokenizer.json; the chat template renders the Qwen3-VL instruct format."""
    from transformers import AutoConfig, AutoTokenizer, Qwen2VLImageProcessor, Qwen3VLVideoProcessor

    hf = AutoTokenizer.from_pretrained(repo_id)
    raw = Tokenizer.from_file(str(snapshot / "tokenizer.json"))
    for s in TOKENIZER_CHECK_TEXTS:
        a = hf(s)["input_ids"]
        b = raw.encode(s).ids
        c = tok.encode(s).ids
        if not (a == b == c):
            raise RuntimeError(f"tokenizer mismatch on {s!r}: {a} / {b} / {c}")
        if hf.decode(a) != raw.decode(b, skip_special_tokens=False):
            raise RuntimeError(f"decode mismatch on {s!r}")
    if hf.padding_side != "left" or hf.pad_token != "<|endoftext|>" or hf.bos_token is not None:
        raise RuntimeError(f"tokenizer settings: {hf.padding_side} {hf.pad_token} {hf.bos_token}")
    ids = special_ids(tok)
    for content, i in ids.items():
        if hf.convert_tokens_to_ids(content) != i:
            raise RuntimeError(f"{content}: {hf.convert_tokens_to_ids(content)} != {i}")
    msgs = [
        {
            "role": "user",
            "content": [
                {"type": "image", "image": None},
                {"type": "image", "image": None},
                {"type": "text", "text": "go"},
            ],
        }
    ]
    want = (
        "<|im_start|>user\n<|vision_start|><|image_pad|><|vision_end|><|vision_start|><|image_pad|><|vision_end|>"
        "go<|im_end|>\n"
    )
    got = hf.apply_chat_template(msgs, tokenize=False, add_generation_prompt=False)
    if got != want:
        raise RuntimeError(f"chat template gave {got!r}")
    got = hf.apply_chat_template(msgs, tokenize=False, add_generation_prompt=True)
    if got != want + "<|im_start|>assistant\n":
        raise RuntimeError(f"chat template (generation prompt) gave {got!r}")
    cfg = AutoConfig.from_pretrained(repo_id)
    rope = cfg.text_config.rope_parameters
    if (
        rope.get("rope_theta") != text["rope_theta"]
        or list(rope.get("mrope_section", [])) != text["rope_scaling"]["mrope_section"]
        or not rope.get("mrope_interleaved")
        or cfg.text_config.vocab_size != vocab_size
        or cfg.image_token_id != ids["<|image_pad|>"]
    ):
        raise RuntimeError(f"config loaded as {cfg}")
    Qwen2VLImageProcessor.from_pretrained(repo_id)
    Qwen3VLVideoProcessor.from_pretrained(repo_id)


def cmd_hub(args) -> None:
    tiny_tok = train_tokenizer(TINY_BASE_VOCAB)
    out = Path(args.out)
    files = backbone_files(
        tiny_tok, vocab_size=TINY_VOCAB_SIZE, text=TINY_TEXT, vision=TINY_VISION, min_pixels=TINY_MIN_PIXELS
    )
    snapshot = write_repo(out, TINY_REPO, TINY_REVISION, files)
    ids = special_ids(tiny_tok)
    (out / "README.md").write_text(
        HUB_README.format(
            repo=TINY_REPO,
            rev=TINY_REVISION,
            vocab_size=TINY_VOCAB_SIZE,
            base=TINY_BASE_VOCAB,
            min_pixels=TINY_MIN_PIXELS,
            ids=", ".join(f"`{c}` {i}" for c, i in ids.items()),
        )
    )
    print(f"wrote {snapshot}")
    if not args.tiny_only:
        full_tok = train_tokenizer(TINY_BASE_VOCAB, fill_to=REAL_BASE_VOCAB)
        full_out = Path(args.full_out)
        full_files = backbone_files(
            full_tok, vocab_size=151936, text=FULL_TEXT, vision=FULL_VISION, min_pixels=QWEN3_VL_MIN_PIXELS
        )
        full_snapshot = write_repo(full_out, FULL_REPO, FULL_REVISION, full_files)
        print(f"wrote {full_snapshot}")
    with hub_cache(out):
        check_backbone_repo(snapshot, TINY_REPO, tiny_tok, vocab_size=TINY_VOCAB_SIZE, text=TINY_TEXT)
    if not args.tiny_only:
        with hub_cache(full_out):
            check_backbone_repo(full_snapshot, FULL_REPO, full_tok, vocab_size=151936, text=FULL_TEXT)
    print("checked: Auto* loaders, ids, chat template and config")


@contextlib.contextmanager
def hub_cache(path: Path):
    """Points huggingface_hub at another cache directory for the duration (its constant is read per call)."""
    import huggingface_hub.constants as hc

    old_env, old_const = os.environ.get("HF_HUB_CACHE"), hc.HF_HUB_CACHE
    os.environ["HF_HUB_CACHE"] = str(path)
    hc.HF_HUB_CACHE = str(path)
    try:
        yield
    finally:
        hc.HF_HUB_CACHE = old_const
        if old_env is None:
            os.environ.pop("HF_HUB_CACHE", None)
        else:
            os.environ["HF_HUB_CACHE"] = old_env


# ----------------------------------------------------------------------------------------------
# Tiny N1.7 network and its raw NVIDIA-layout checkpoint

TINY_IMAGE = {
    "shortest_image_edge": 64,
    "crop_fraction": 0.95,
    "image_target_size": [64, 64],
    "image_crop_size": [60, 60],
}
TINY_SEED = 17
MODEL_HORIZON = 8
VALID_HORIZON = 6


def tiny_model_kwargs() -> dict:
    return dict(
        model_name=TINY_REPO,
        backbone_model_type="qwen",
        select_layer=4,
        backbone_embedding_dim=64,
        hidden_size=32,
        input_embedding_dim=48,
        max_state_dim=16,
        max_action_dim=16,
        action_horizon=MODEL_HORIZON,
        max_num_embodiments=4,
        max_seq_len=16,
        diffusion_model_cfg={
            "positional_embeddings": None,
            "num_layers": 4,
            "num_attention_heads": 4,
            "attention_head_dim": 12,
            "norm_type": "ada_norm",
            "dropout": 0.2,
            "final_dropout": True,
            "output_dim": 32,
            "interleave_self_attention": True,
        },
        vl_self_attention_cfg={
            "positional_embeddings": None,
            "num_layers": 2,
            "num_attention_heads": 4,
            "attention_head_dim": 16,
            "dropout": 0.2,
            "final_dropout": True,
        },
        num_inference_timesteps=4,
        num_timestep_buckets=1000,
        # processing keys as the checkpoint's processor_config.json has them (lerobot reads that file)
        image_target_size=TINY_IMAGE["image_target_size"],
        image_crop_size=TINY_IMAGE["image_crop_size"],
        shortest_image_edge=TINY_IMAGE["shortest_image_edge"],
        crop_fraction=TINY_IMAGE["crop_fraction"],
    )


def init_value(model: torch.nn.Module, name: str, gen: torch.Generator) -> tuple[torch.Tensor, str]:
    """Fresh float32 values for one parameter, drawn from `gen`: norm weights 1 + 0.1 N(0,1), biases 0.05 N(0,1),
    embedding tables N(0,1) (token) or 0.5 N(0,1) (position tables), matrices N(0,1)/sqrt(fan_in) (fan_in = input
    width; nn.Linear stores [out, in], the category-specific layers [C, in, out], the patch Conv3d [out, c, t, h, w]).
    Returns the values and the rule's name."""
    mname, _, pname = name.rpartition(".")
    module = model.get_submodule(mname)
    shape = tuple(getattr(module, pname).shape)
    kind = type(module).__name__
    noise = torch.randn(shape, generator=gen, dtype=torch.float32)
    if ("Norm" in kind) and pname == "weight":
        return noise.mul_(0.1).add_(1.0), "norm weight"
    if pname in ("bias", "b"):
        return noise.mul_(0.05), "bias"
    if isinstance(module, torch.nn.Embedding):
        scale = 1.0 if name.endswith("embed_tokens.weight") else 0.5
        return noise.mul_(scale), f"embedding x{scale}"
    if kind == "CategorySpecificLinear":
        return noise.div_(shape[1] ** 0.5), "category matrix"
    if len(shape) >= 2:
        return noise.div_(float(np.prod(shape[1:])) ** 0.5), "matrix"
    raise RuntimeError(f"no init rule for {name} {shape} ({kind})")


def randomize_parameters(model: torch.nn.Module, seed: int) -> dict:
    """Every parameter gets fresh seeded values (init_value, in named_parameters order, one generator), so nothing
    is left at zero or identity; returns how many tensors each rule covered."""
    gen = torch.Generator().manual_seed(seed)
    rules: dict[str, int] = {}
    with torch.no_grad():
        for name, p in model.named_parameters():
            value, rule = init_value(model, name, gen)
            p.copy_(value.to(p.dtype))
            rules[rule] = rules.get(rule, 0) + 1
    return rules


EMBODIMENTS = {
    # LIBERO-like single-arm end-effector layout, one camera, enum names in upper case
    "libero_sim": dict(
        index=2,
        video=["image"],
        state=[("x", 1), ("y", 1), ("z", 1), ("roll", 1), ("pitch", 1), ("yaw", 1), ("gripper", 1)],
        action=[("x", 1), ("y", 1), ("z", 1), ("roll", 1), ("pitch", 1), ("yaw", 1), ("gripper", 1)],
        action_types=["EEF"] * 6 + ["NON_EEF"],
        enum_case="upper",
        language="annotation.human.action.task_description",
        degenerate={"action": ("yaw", 0)},
        horizon=VALID_HORIZON,
        seed=41,
    ),
    # joint-space arm + gripper, two cameras, a state-only base group, enum values in lower case
    "new_embodiment": dict(
        index=1,
        video=["front", "wrist"],
        state=[("arm", 6), ("gripper", 1), ("base", 2)],
        action=[("arm", 6), ("gripper", 1)],
        action_types=["NON_EEF", "NON_EEF"],
        enum_case="lower",
        language="annotation.human.task_description",
        degenerate={"state": ("base", 1)},
        horizon=VALID_HORIZON,
        seed=43,
    ),
}


def group_stats(gen: np.random.Generator, dim: int, degenerate_at: int | None) -> dict[str, list[float]]:
    """min/max/mean/std/q01/q99 of one group, as decimal numbers with 6 digits (not float32-exact)."""
    mean = gen.uniform(-2.0, 2.0, dim)
    std = gen.uniform(0.05, 0.8, dim)
    q01 = mean - gen.uniform(1.8, 2.4, dim) * std
    q99 = mean + gen.uniform(1.8, 2.4, dim) * std
    lo = q01 - gen.uniform(0.1, 0.6, dim) * std
    hi = q99 + gen.uniform(0.1, 0.6, dim) * std
    stats = {"max": hi, "mean": mean, "min": lo, "q01": q01, "q99": q99, "std": std}
    if degenerate_at is not None:  # a dimension that never moved in the data
        for key in stats:
            stats[key] = stats[key].copy()
            stats[key][degenerate_at] = mean[degenerate_at]
        stats["std"][degenerate_at] = 0.0
    return {k: [round(float(x), 6) for x in v] for k, v in stats.items()}


def embodiment_statistics(emb: dict) -> dict:
    gen = np.random.default_rng(emb["seed"])
    out: dict[str, dict] = {"state": {}, "action": {}, "relative_action": {}}
    for modality in ("state", "action"):
        deg = emb["degenerate"].get(modality)
        for key, dim in emb[modality]:
            out[modality][key] = group_stats(gen, dim, deg[1] if deg and deg[0] == key else None)
    return out


def modality_config(emb: dict) -> dict:
    def enum(text: str) -> str:
        return text.upper() if emb["enum_case"] == "upper" else text.lower()

    return {
        "video": {"delta_indices": [0], "modality_keys": list(emb["video"])},
        "state": {"delta_indices": [0], "modality_keys": [k for k, _ in emb["state"]]},
        "action": {
            "delta_indices": list(range(emb["horizon"])),
            "modality_keys": [k for k, _ in emb["action"]],
            "action_configs": [
                {"rep": enum("absolute"), "type": enum(t), "format": enum("default"), "state_key": None}
                for t in emb["action_types"]
            ],
        },
        "language": {"delta_indices": [0], "modality_keys": [emb["language"]]},
    }


def processor_config(image: dict, embodiments: dict, *, max_state_dim: int, max_action_dim: int, model_name: str,
                     horizon: int) -> dict:
    """processor_config.json as Isaac-GR00T's Gr00tN1d7Processor.save_pretrained lays it out (the keys lerobot's
    _load_n1_7_checkpoint_processor_assets reads, plus the ones upstream writes next to them)."""
    return {
        "processor_class": "Gr00tN1d7Processor",
        "processor_kwargs": {
            "apply_sincos_state_encoding": False,
            "clip_outliers": True,
            "color_jitter_params": None,
            "crop_fraction": image["crop_fraction"],
            "exclude_state": False,
            "formalize_language": True,
            "image_crop_size": image["image_crop_size"],
            "image_target_size": image["image_target_size"],
            "letter_box_transform": False,
            "max_action_dim": max_action_dim,
            "max_action_horizon": horizon,
            "max_state_dim": max_state_dim,
            "modality_configs": {tag: modality_config(emb) for tag, emb in embodiments.items()},
            "model_name": model_name,
            "model_type": "Gr00tN1d7",
            "random_rotation_angle": None,
            "shortest_image_edge": image["shortest_image_edge"],
            "state_dropout_prob": 0.0,
            "use_albumentations": True,
            "use_mean_std": False,
            "use_percentiles": True,
            "use_relative_action": False,
        },
    }


def write_sidecars(ckpt: Path, embodiments: dict, *, image: dict, max_state_dim: int, max_action_dim: int,
                   model_name: str, horizon: int) -> None:
    pc = processor_config(
        image, embodiments, max_state_dim=max_state_dim, max_action_dim=max_action_dim, model_name=model_name,
        horizon=horizon,
    )
    (ckpt / "processor_config.json").write_text(dump_json(pc))
    (ckpt / "statistics.json").write_text(dump_json({tag: embodiment_statistics(e) for tag, e in embodiments.items()}))
    (ckpt / "embodiment_id.json").write_text(dump_json({tag: e["index"] for tag, e in embodiments.items()}))


def build_tiny_checkpoint(ckpt: Path) -> dict:
    """Upstream GR00TN17 with seeded random weights, saved by upstream's save_pretrained in bfloat16 (the dtype
    of the released checkpoints and of GR00T_N1_7_DEFAULTS) as 3 shards + index, then the three sidecar files."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17, GR00TN17Config

    if ckpt.exists():
        shutil.rmtree(ckpt)
    torch.manual_seed(TINY_SEED)
    model = GR00TN17(GR00TN17Config(**tiny_model_kwargs()), load_backbone_weights=False)
    rules = randomize_parameters(model, TINY_SEED)
    model = model.to(torch.bfloat16)
    with contextlib.redirect_stderr(io.StringIO()):
        model.save_pretrained(str(ckpt), max_shard_size="600KB")
    shards = sorted(p.name for p in ckpt.glob("model-*.safetensors"))
    if len(shards) < 2 or not (ckpt / "model.safetensors.index.json").exists() or (ckpt / "model.safetensors").exists():
        raise RuntimeError(f"unexpected shard layout: {sorted(p.name for p in ckpt.iterdir())}")
    for shard in ckpt.iterdir():
        shard.chmod(0o644)
    write_sidecars(
        ckpt, EMBODIMENTS, image=TINY_IMAGE, max_state_dim=16, max_action_dim=16, model_name=TINY_REPO,
        horizon=MODEL_HORIZON,
    )
    return {"init_rules": rules, "shards": shards, "parameters": sum(p.numel() for p in model.parameters())}


# ----------------------------------------------------------------------------------------------
# Fixture cases

CASES = {
    "cam1_libero": dict(
        desc=(
            "libero_sim (embodiment row 2), 1 camera 128x128 PNG: cv2 INTER_AREA 2:1 down to 64x64, centre crop "
            "60x60, INTER_AREA back up to 64x64; Qwen smart_resize takes the minimum-pixels branch (4096 < 6144) "
            "and bicubic-upscales to 96x96 (6x6 patches, 9 image tokens); state/action groups "
            "x,y,z,roll,pitch,yaw,gripper (1 each), two state values beyond q01/q99 (clipped); action 'yaw' has "
            "q01 == q99 (decodes to q01); the libero decode transform maps the gripper to -sign(2g - 1)"
        ),
        tag="libero_sim",
        cameras=[("image", (128, 128))],
        instruction="put the black bowl on the plate",
        state_norm=[-0.35, 0.6, 1.3, -0.9, 0.1, -1.25, 0.75],
        seed=1000,
    ),
    "cam2_new": dict(
        desc=(
            "new_embodiment (row 1), 2 cameras, both 128x129 PNG (lerobot stacks the cameras of one observation "
            "into one array, so they must share a size): the shorter-side resize computes a width of "
            "round(64.5) = 64 with Python's half-to-even rounding, so INTER_AREA to 64x64, crop 60x60, 64x64, then "
            "the minimum-pixels branch to 96x96 (6x6 patches each); state groups arm(6), gripper(1), base(2) with "
            "base[1] degenerate (q01 == q99, normalises to 0) and the gripper beyond q99; action groups arm(6), "
            "gripper(1); no decode transform"
        ),
        tag="new_embodiment",
        cameras=[("front", (128, 129)), ("wrist", (128, 129))],
        instruction="Pick up the red cube and place it in the bowl.",
        state_norm=[0.2, -0.5, 0.9, -0.1, 0.45, -0.75, 1.5, 0.3, 0.0],
        seed=2000,
    ),
    "long_instruction": dict(
        desc=(
            "libero_sim, 1 portrait camera 160x90 PNG (INTER_AREA to 114x64, crop 108x60, INTER_AREA up to 115x64; "
            "smart_resize rounds 115 to 128 and bicubic-upscales to 128x64 = 8x4 patches, 4x2 merged tokens); a "
            "long instruction with upper case, digits, punctuation, an underscore, an apostrophe and a non-ASCII "
            "letter: formalize_language lower-cases it and drops every character that is not alphanumeric, "
            "whitespace or '_' (the apostrophe goes, 'é' stays)"
        ),
        tag="libero_sim",
        cameras=[("image", (160, 90))],
        instruction=(
            "Pick up the RED mug (the one on the LEFT), then put it 3 cm behind the blue_plate; don't spill the "
            "café! Afterwards close the top drawer, turn the knob by 90 degrees and wait 5 seconds."
        ),
        state_norm=[0.5, -0.2, 0.05, 0.95, -0.6, 0.3, -0.8],
        seed=3000,
    ),
    "cam2_nonsquare": dict(
        desc=(
            "new_embodiment, 2 landscape cameras, both 64x143 PNG (shorter side already 64: no first resize; crop "
            "60x135; INTER_AREA to 64x144; smart_resize's round(144 / 32) = round(4.5) = 4 (half-to-even) gives "
            "64x128, a bicubic downscale of the width; 4x8 patches, 2x4 merged tokens each), so H != W in the "
            "position-table interpolation and in M-RoPE; an empty instruction becomes 'Perform the task.' and, "
            "formalised, 'perform the task'"
        ),
        tag="new_embodiment",
        cameras=[("front", (64, 143)), ("wrist", (64, 143))],
        instruction="",
        state_norm=[-0.7, 0.15, 0.65, -1.1, 0.4, -0.05, 0.85, -0.45, 0.0],
        seed=4000,
    ),
}


def raw_state(tag: str, targets: list[float]) -> list[float]:
    """Robot-unit state whose q01/q99 normalisation is about `targets` (values outside [-1, 1] get clipped);
    a degenerate dimension (q01 == q99) gets q01 + 0.25, which normalises to 0 whatever its value."""
    stats = embodiment_statistics(EMBODIMENTS[tag])["state"]
    lo = [v for key, _ in EMBODIMENTS[tag]["state"] for v in stats[key]["q01"]]
    hi = [v for key, _ in EMBODIMENTS[tag]["state"] for v in stats[key]["q99"]]
    assert len(lo) == len(targets)
    return [
        round(a + 0.25, 5) if a == b else round(a + (n + 1.0) / 2.0 * (b - a), 5)
        for a, b, n in zip(lo, hi, targets, strict=True)
    ]


def draw_frame(h: int, w: int, seed: int) -> np.ndarray:
    """uint8 RGB: two-direction colour gradients, a few flat blocks and per-pixel noise."""
    gen = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = gen.uniform(50, 200, 3)
    gy, gx = gen.uniform(-90, 90, 3), gen.uniform(-90, 90, 3)
    arr = base + yy[..., None] / h * gy + xx[..., None] / w * gx
    for _ in range(3):
        y0, x0 = int(gen.integers(0, h - 4)), int(gen.integers(0, w - 4))
        y1, x1 = y0 + int(gen.integers(3, max(4, h // 3))), x0 + int(gen.integers(3, max(4, w // 3)))
        arr[y0:y1, x0:x1] = gen.uniform(0, 255, 3)
    arr = arr + gen.normal(0.0, 10.0, arr.shape)
    return np.clip(np.rint(arr), 0, 255).astype(np.uint8)


def decode_png(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def write_inputs(case_dir: Path, cameras, seed: int) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    inputs = case_dir / "inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    images, files = {}, {}
    for i, (key, (h, w)) in enumerate(cameras):
        arr = draw_frame(h, w, seed + 10 * i)
        name = f"{key}.png"
        Image.fromarray(arr, "RGB").save(inputs / name, format="PNG")
        back = decode_png(inputs / name)
        assert np.array_equal(back, arr)
        images[key], files[key] = back, f"inputs/{name}"
    return images, files


class Probes:
    """Forward hooks and instance-level wrappers on upstream modules: they record and call through."""

    def __init__(self, policy, pre):
        from lerobot.policies.groot.processor_groot import GrootN17VLMEncodeStep

        self.handles = []
        self.rec: dict[str, list] = {}
        model = policy._groot_model
        qwen = model.backbone.model.model
        visual, lm = qwen.visual, qwen.language_model
        head = model.action_head

        def keep(name):
            def hook(_m, _inp, out):
                self.rec.setdefault(name, []).append(out.detach().clone())

            return hook

        self.handles.append(visual.patch_embed.register_forward_hook(keep("vision.patch_embed")))
        self.handles.append(
            visual.blocks[0].register_forward_pre_hook(
                lambda _m, args: self.rec.setdefault("vision.embeddings", []).append(args[0].detach().clone())
            )
        )
        for i, blk in enumerate(visual.blocks):
            self.handles.append(blk.register_forward_hook(keep(f"vision.block.{i}")))
        for k, merger in enumerate(visual.deepstack_merger_list):
            self.handles.append(merger.register_forward_hook(keep(f"vision.deepstack.{k}")))
        self.handles.append(visual.merger.register_forward_hook(keep("vision.merged")))
        orig_interp = visual.fast_pos_embed_interpolate

        def interp(grid_thw):
            out = orig_interp(grid_thw)
            self.rec.setdefault("vision.pos_embed", []).append(out.detach().clone())
            return out

        visual.fast_pos_embed_interpolate = interp

        def lm_pre(_m, _args, kwargs):
            self.rec.setdefault("llm.position_ids", []).append(kwargs["position_ids"].detach().clone())
            self.rec.setdefault("llm.inputs_embeds", []).append(kwargs["inputs_embeds"].detach().clone())
            self.rec.setdefault("llm.attention_mask", []).append(kwargs["attention_mask"].detach().clone())

        self.handles.append(lm.register_forward_pre_hook(lm_pre, with_kwargs=True))
        for i, layer in enumerate(lm.layers):
            self.handles.append(layer.register_forward_hook(keep(f"llm.layer.{i}")))
        self.handles.append(head.vlln.register_forward_hook(keep("head.vlln")))
        self.handles.append(head.vl_self_attention.register_forward_hook(keep("head.vl_self_attention")))
        self.handles.append(head.state_encoder.register_forward_hook(keep("head.state_features")))
        self.handles.append(head.model.timestep_encoder.register_forward_hook(keep("head.temb")))
        self.handles.append(head.action_encoder.register_forward_hook(keep("head.action_encoder")))
        for i, blk in enumerate(head.model.transformer_blocks):
            self.handles.append(blk.register_forward_hook(keep(f"head.dit_block.{i}")))
        self.handles.append(head.model.register_forward_hook(keep("head.dit_out")))
        self.handles.append(head.action_decoder.register_forward_hook(keep("head.decoder_out")))

        def backbone_out(_m, _inp, out):
            self.rec.setdefault("backbone.image_mask", []).append(out["image_mask"].detach().clone())
            self.rec.setdefault("backbone.attention_mask", []).append(out["backbone_attention_mask"].detach().clone())
            self.rec.setdefault("backbone.features", []).append(out["backbone_features"].detach().clone())

        self.handles.append(model.backbone.register_forward_hook(backbone_out))

        vlm_steps = [s for s in pre.steps if isinstance(s, GrootN17VLMEncodeStep)]
        assert len(vlm_steps) == 1
        self.vlm_step = vlm_steps[0]
        orig_build = self.vlm_step._build_sample_images

        def build(video, batch_size, target_device):
            out = orig_build(video, batch_size, target_device)
            self.rec["vlm_images"] = [[np.array(img) for img in frames] for frames in out]
            return out

        self.vlm_step._build_sample_images = build
        proc = self.vlm_step.proc
        orig_template = proc.apply_chat_template

        def template(conversation, *args, **kwargs):
            text = orig_template(conversation, *args, **kwargs)
            self.rec.setdefault("prompt", []).append(text)
            self.rec.setdefault("language", []).append(
                [item["text"] for item in conversation[0]["content"] if item.get("type") == "text"]
            )
            return text

        proc.apply_chat_template = template
        image_processor = proc.image_processor
        orig_resize = image_processor.resize

        def resize(*args, **kwargs):
            out = orig_resize(*args, **kwargs)
            self.rec.setdefault("qwen_images", []).append(out.detach().clone())
            return out

        image_processor.resize = resize

    def one(self, name: str) -> torch.Tensor:
        values = self.rec[name]
        if len(values) != 1:
            raise RuntimeError(f"{name} recorded {len(values)} times")
        return values[0]

    def remove(self) -> None:
        for h in self.handles:
            h.remove()


@contextlib.contextmanager
def injected_noise(head, noise: torch.Tensor, log: list):
    """Replaces torch.randn only while GR00TN17ActionHead.get_action_with_features runs (upstream draws the
    initial action noise there, with torch.randn(size=(B, action_horizon, max_action_dim), dtype=vl_embeds.dtype,
    device=vl_embeds.device)) and returns `noise` instead; every call is logged."""
    orig_method = head.get_action_with_features

    def with_noise(*args, **kwargs):
        real_randn = torch.randn

        def fake_randn(*r_args, **r_kwargs):
            size = r_kwargs.get("size", r_args[0] if r_args else None)
            log.append({"size": list(size), "dtype": str(r_kwargs.get("dtype")), "device": str(r_kwargs.get("device"))})
            if tuple(size) != tuple(noise.shape):
                raise RuntimeError(f"torch.randn called with size {size}, expected {tuple(noise.shape)}")
            return noise.clone().to(dtype=r_kwargs.get("dtype") or noise.dtype, device=r_kwargs.get("device") or "cpu")

        torch.randn = fake_randn
        try:
            return orig_method(*args, **kwargs)
        finally:
            torch.randn = real_randn

    head.get_action_with_features = with_noise
    try:
        yield
    finally:
        del head.get_action_with_features


def groot_config(ckpt: Path, spec: dict):
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.groot.configuration_groot import GrootConfig

    emb = EMBODIMENTS[spec["tag"]]
    state_dim = sum(d for _, d in emb["state"])
    action_dim = sum(d for _, d in emb["action"])
    input_features = {
        f"observation.images.{key}": PolicyFeature(type=FeatureType.VISUAL, shape=(3, h, w))
        for key, (h, w) in spec["cameras"]
    }
    input_features["observation.state"] = PolicyFeature(type=FeatureType.STATE, shape=(state_dim,))
    return GrootConfig(
        base_model_path=str(ckpt),
        embodiment_tag=spec["tag"],
        input_features=input_features,
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))},
        max_state_dim=16,
        max_action_dim=16,
        chunk_size=MODEL_HORIZON,
        n_action_steps=MODEL_HORIZON,
        use_bf16=False,
        device="cpu",
        push_to_hub=False,
    )


def load_policy(ckpt: Path, spec: dict):
    """GrootPolicy.from_pretrained on the raw checkpoint (it calls GR00TN17.from_pretrained on the absolute path and
    casts every parameter to float32), and lerobot's processor factory for it. Checks that every tensor in the
    shards was loaded and that every parameter of the model came from the shards."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.groot.modeling_groot import GrootPolicy
    from lerobot.policies.groot.processor_groot import GrootN17VLMEncodeStep
    from safetensors.torch import load_file

    cfg = groot_config(ckpt, spec)
    policy = GrootPolicy.from_pretrained(str(ckpt), config=cfg)
    policy.eval()
    model = policy._groot_model
    saved: dict[str, torch.Tensor] = {}
    index = json.loads((ckpt / "model.safetensors.index.json").read_text())
    for shard in sorted(set(index["weight_map"].values())):
        saved.update(load_file(str(ckpt / shard)))
    state = model.state_dict()
    for key, value in saved.items():
        if key not in state:
            raise RuntimeError(f"{key} in the shards but not in the model")
        if not torch.equal(state[key], value.to(state[key].dtype)):
            raise RuntimeError(f"{key} differs after loading {ckpt}")
    tied = {"backbone.model.lm_head.weight": "backbone.model.model.language_model.embed_tokens.weight"}
    missing = [k for k in state if k not in saved and k not in tied]
    if missing:
        raise RuntimeError(f"not loaded from the shards: {missing[:8]}")
    if not model.backbone.model.lm_head.weight is model.backbone.model.model.language_model.embed_tokens.weight:
        raise RuntimeError("lm_head is not tied to embed_tokens")
    dtypes = sorted({str(p.dtype) for p in model.parameters()})
    rope = check_rope_buffers(model)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(ckpt))
    vlm = [s for s in pre.steps if isinstance(s, GrootN17VLMEncodeStep)]
    assert len(vlm) == 1 and vlm[0]._proc is None
    upstream_name = vlm[0].model_name
    vlm[0].model_name = TINY_REPO  # replaced: upstream hard-codes "nvidia/Cosmos-Reason2-2B"
    info = {"param_dtypes": dtypes, "upstream_vlm_model_name": upstream_name, "n_loaded": len(saved), "rope": rope}
    return cfg, policy, pre, post, info


def check_rope_buffers(model) -> str:
    """The rotary frequency buffers after loading a bfloat16 checkpoint are the float32 formulas (not values
    rounded through bfloat16): text 1 / theta^(2j / head_dim), vision 1 / 10000^(2j / (vision head_dim / 2))."""
    qwen = model.backbone.model.model
    tcfg = qwen.language_model.config
    head_dim = tcfg.head_dim
    theta = float(tcfg.rope_parameters["rope_theta"])
    want_text = 1.0 / (theta ** (torch.arange(0, head_dim, 2, dtype=torch.int64).float() / head_dim))
    vdim = (qwen.visual.config.hidden_size // qwen.visual.config.num_heads) // 2
    want_vision = 1.0 / (10000.0 ** (torch.arange(0, vdim, 2, dtype=torch.float) / vdim))
    got_text = qwen.language_model.rotary_emb.inv_freq
    got_vision = qwen.visual.rotary_pos_emb.inv_freq
    if not (torch.equal(got_text, want_text) and torch.equal(got_vision, want_vision)):
        raise RuntimeError(f"rotary buffers differ: {got_text} vs {want_text}; {got_vision} vs {want_vision}")
    return "text and vision inv_freq equal the float32 formulas exactly"


def run_case(name: str, spec: dict, out_root: Path, shared_ckpt: Path, build_info: dict) -> Path:
    from lerobot.policies.groot.processor_groot import GrootN17PackInputsStep

    case_dir = out_root / name
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    ckpt = case_dir / "checkpoint"
    shutil.copytree(shared_ckpt, ckpt)
    images, files = write_inputs(case_dir, spec["cameras"], spec["seed"])
    state = torch.tensor([raw_state(spec["tag"], spec["state_norm"])], dtype=torch.float32)
    noise = torch.randn((1, MODEL_HORIZON, 16), generator=torch.Generator().manual_seed(spec["seed"] + 1))

    cfg, policy, pre, post, load_info = load_policy(ckpt.resolve(), spec)
    probes = Probes(policy, pre)
    batch = {
        f"observation.images.{key}": torch.from_numpy(arr).permute(2, 0, 1).unsqueeze(0).contiguous()
        for key, arr in images.items()
    }
    batch["observation.state"] = state.clone()
    batch["task"] = spec["instruction"]
    randn_log: list = []
    get_action_out: list = []
    model = policy._groot_model
    orig_get_action = model.get_action

    def get_action(inputs, options=None):
        out = orig_get_action(inputs, options)
        get_action_out.append({k: v.detach().clone() for k, v in out.items()})
        return out

    model.get_action = get_action
    with torch.no_grad(), injected_noise(model.action_head, noise, randn_log):
        processed = pre(batch)
        actions_chunk = policy.predict_action_chunk(processed)
        actions = post(actions_chunk)
    del model.get_action
    probes.remove()
    if len(randn_log) != 1 or len(get_action_out) != 1:
        raise RuntimeError(f"noise draws {randn_log}, get_action calls {len(get_action_out)}")

    pack = [s for s in pre.steps if isinstance(s, GrootN17PackInputsStep)][0]
    cams = [key for key, _ in spec["cameras"]]
    rec = probes.rec
    t: dict[str, torch.Tensor] = {"input.state": state, "input.noise": noise.clone()}
    for key in cams:
        t[f"input.image.{key}"] = torch.from_numpy(images[key]).unsqueeze(0)
    vlm_images = rec["vlm_images"][0]
    assert len(vlm_images) == len(cams)
    for key, img in zip(cams, vlm_images, strict=True):
        t[f"pre.vlm_image.{key}"] = torch.from_numpy(np.ascontiguousarray(img))
    qwen_images = probes.one("qwen_images")  # one call: all cameras of a case share a size
    assert qwen_images.dtype == torch.uint8 and qwen_images.shape[0] == len(cams)
    for key, img in zip(cams, qwen_images, strict=True):
        t[f"pre.qwen_image.{key}"] = img.permute(1, 2, 0).contiguous()
    t["pre.state"] = processed["state"].float()
    t["pre.embodiment_id"] = processed["embodiment_id"]
    t["pre.action_mask"] = processed["action_mask"].float()
    for key in ("input_ids", "attention_mask", "image_grid_thw", "mm_token_type_ids"):
        t[f"pre.{key}"] = processed[key]
    t["pre.pixel_values"] = processed["pixel_values"].float()

    pos4 = probes.one("llm.position_ids")
    if pos4.shape[0] != 4 or not torch.equal(pos4[0], pos4[1]):
        raise RuntimeError(f"unexpected position ids {pos4.shape}")
    t["mid.position_ids"] = pos4[1:].contiguous()
    t["mid.image_mask"] = probes.one("backbone.image_mask").to(torch.uint8)
    t["mid.vision.patch_embed"] = probes.one("vision.patch_embed")
    t["mid.vision.pos_embed"] = probes.one("vision.pos_embed")
    t["mid.vision.embeddings"] = probes.one("vision.embeddings")
    for i in range(len(model.backbone.model.model.visual.blocks)):
        t[f"mid.vision.block.{i}"] = probes.one(f"vision.block.{i}")
    for k in range(len(model.backbone.model.model.visual.deepstack_merger_list)):
        t[f"mid.vision.deepstack.{k}"] = probes.one(f"vision.deepstack.{k}")
    t["mid.vision.merged"] = probes.one("vision.merged")
    t["mid.llm.inputs_embeds"] = probes.one("llm.inputs_embeds")
    n_layers = len(model.backbone.language_model.layers)
    for i in range(n_layers):
        t[f"mid.llm.layer.{i}"] = probes.one(f"llm.layer.{i}")
    features = probes.one("backbone.features")
    if not torch.equal(features, t[f"mid.llm.layer.{n_layers - 1}"]):
        raise RuntimeError("backbone features are not the last kept layer's output")
    t["mid.backbone_features"] = features
    t["mid.vl_embeds.vlln"] = probes.one("head.vlln")
    t["mid.vl_embeds"] = probes.one("head.vl_self_attention")
    t["mid.state_features"] = probes.one("head.state_features")
    steps = model.action_head.num_inference_timesteps
    for name_, key in (("head.temb", "temb"), ("head.action_encoder", "action_encoder"), ("head.dit_out", "dit_out"),
                       ("head.decoder_out", "decoder_out")):
        if len(rec[name_]) != steps:
            raise RuntimeError(f"{name_} ran {len(rec[name_])} times")
        for k in range(steps):
            if key in ("temb", "decoder_out") or k == 0:
                t[f"mid.{key}.step{k}"] = rec[name_][k]
    for k in range(steps):
        t[f"mid.velocity.step{k}"] = rec["head.decoder_out"][k][:, -MODEL_HORIZON:].contiguous()
    for i in range(len(model.action_head.model.transformer_blocks)):
        t[f"mid.dit_block.{i}.step0"] = rec[f"head.dit_block.{i}"][0]
    out = get_action_out[0]
    t["out.action_pred"] = out["action_pred"]
    if not torch.equal(out["backbone_features"], t["mid.vl_embeds"]) or not torch.equal(
        out["state_features"], t["mid.state_features"]
    ):
        raise RuntimeError("get_action outputs differ from the hooked tensors")
    t["out.actions_chunk"] = actions_chunk
    t["out.actions"] = actions
    for key, value in t.items():
        if value.dtype == torch.bool:
            t[key] = value.to(torch.uint8)
        t[key] = t[key].detach().contiguous()
    for key, value in t.items():
        if value.is_floating_point() and value.dtype != torch.float32:
            raise RuntimeError(f"{key} is {value.dtype}")

    prompt = rec["prompt"]
    language = rec["language"]
    assert len(prompt) == 1 and len(language) == 1
    tok = probes.vlm_step.proc.tokenizer
    emb = EMBODIMENTS[spec["tag"]]
    qwen_cfg = model.backbone.model.config
    meta = {
        "versions": json.dumps(versions()),
        "case": spec["desc"],
        "instruction": spec["instruction"],
        "language": language[0][0],
        "prompt": prompt[0],
        "prompt_tokens_decoded": tok.decode(processed["input_ids"][0].tolist(), skip_special_tokens=False),
        "embodiment_tag": spec["tag"],
        "embodiment_id": str(int(processed["embodiment_id"][0])),
        "cameras": json.dumps([f"observation.images.{k}" for k in cams]),
        "camera_keys": json.dumps(cams),
        "input_files": json.dumps(files),
        "state_groups": json.dumps(emb["state"]),
        "action_groups": json.dumps(emb["action"]),
        "seed": json.dumps({"inputs": spec["seed"], "noise": spec["seed"] + 1, "weights": TINY_SEED}),
        "noise_injection": json.dumps(
            {
                "how": "torch.randn replaced only while GR00TN17ActionHead.get_action_with_features ran; the "
                "replacement returned input.noise (cast to the requested dtype/device)",
                "calls": randn_log,
                "noise": "torch.randn((1, 8, 16), generator=torch.Generator().manual_seed(seed + 1)), float32",
            }
        ),
        "replaced": json.dumps(
            {
                "GrootN17VLMEncodeStep.model_name": {
                    "value": TINY_REPO,
                    "upstream": load_info["upstream_vlm_model_name"],
                    "why": "make_groot_pre_post_processors hard-codes the Cosmos-Reason2-2B repository for the "
                    "Qwen3-VL processor; the attribute was set before the step first built its processor",
                },
                "torch.randn": "during get_action_with_features only (see noise_injection)",
                "hub": f"HF_HUB_CACHE = tests/fixtures/gr00t_hub (the stand-in repository {TINY_REPO})",
            }
        ),
        "run": json.dumps(
            {
                "loader": "GrootPolicy.from_pretrained(<absolute checkpoint dir>, config=GrootConfig(...)) -> "
                "GR00TN17.from_pretrained; parameters cast to float32 (model_params_fp32)",
                "processors": "lerobot.policies.factory.make_pre_post_processors(config, pretrained_path=ckpt) "
                "(raw N1.7 checkpoint path: make_groot_pre_post_processors)",
                "inference": "pre(batch) -> GrootPolicy.predict_action_chunk (use_bf16=False: no autocast) -> "
                "GR00TN17.get_action -> post",
                "batch": "observation.images.<key>: uint8 [1, 3, H, W] from the PNG, observation.state float32 "
                "[1, D], task: the instruction string",
                "attention": str(getattr(qwen_cfg, "_attn_implementation", None)),
                "torch_threads": torch.get_num_threads(),
                "param_dtypes_after_load": load_info["param_dtypes"],
                "buffer_dtypes_after_load": {k: str(b.dtype) for k, b in model.named_buffers()},
                "checkpoint_file_dtype": "bfloat16",
                "tensors_loaded": load_info["n_loaded"],
                "rotary_buffers": load_info["rope"],
            }
        ),
        "config": json.dumps(
            {
                "model": tiny_model_kwargs(),
                "backbone_config_json": {"text": TINY_TEXT, "vision": TINY_VISION, "vocab_size": TINY_VOCAB_SIZE},
                "special_token_ids": {c: tok.convert_tokens_to_ids(c) for c, _ in QWEN3_VL_ADDED},
                "image_processor": {"min_pixels": TINY_MIN_PIXELS, "max_pixels": QWEN3_VL_MAX_PIXELS},
                "vlm_step": {
                    "shortest_image_edge": probes.vlm_step.shortest_image_edge,
                    "crop_fraction": probes.vlm_step.crop_fraction,
                    "image_target_size": probes.vlm_step.image_target_size,
                    "image_crop_size": probes.vlm_step.image_crop_size,
                    "use_albumentations": probes.vlm_step.use_albumentations,
                    "letter_box_transform": probes.vlm_step.letter_box_transform,
                },
                "pack_step": {
                    "valid_action_horizon": pack.valid_action_horizon,
                    "action_horizon": pack.action_horizon,
                    "use_percentiles": pack.use_percentiles,
                    "clip_outliers": pack.clip_outliers,
                    "formalize_language": pack.formalize_language,
                    "video_modality_keys": pack.video_modality_keys,
                },
                "action_decode_transform": cfg.action_decode_transform,
                "init": build_info["init_rules"],
                "parameters": build_info["parameters"],
                "shards": build_info["shards"],
            }
        ),
        "generator": "tools/oracle/run.sh gr00t_oracle.py fixtures",
    }
    write_safetensors(case_dir / "oracle.safetensors", t, meta)
    from safetensors import safe_open

    with safe_open(str(case_dir / "oracle.safetensors"), "pt") as f:
        assert set(f.keys()) == set(t) and all(torch.equal(f.get_tensor(k), t[k]) for k in t)
    return case_dir


def versions() -> dict:
    import diffusers
    import huggingface_hub
    import lerobot
    import safetensors
    import tokenizers
    import transformers

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "transformers": transformers.__version__,
        "lerobot": getattr(lerobot, "__version__", "unknown"),
        "diffusers": diffusers.__version__,
        "tokenizers": tokenizers.__version__,
        "numpy": np.__version__,
        "safetensors": safetensors.__version__,
        "huggingface_hub": huggingface_hub.__version__,
    }


def ensure_tiny_hub() -> None:
    repo = HUB_CACHE / ("models--" + TINY_REPO.replace("/", "--"))
    if not (repo / "refs" / "main").exists():
        raise SystemExit(f"no stand-in hub cache at {HUB_CACHE}; run `gr00t_oracle.py hub` first")


def cmd_fixtures(args) -> None:
    ensure_tiny_hub()
    out = Path(args.out or REPO_ROOT / "tests" / "fixtures" / "gr00t_n17")
    out.mkdir(parents=True, exist_ok=True)
    names = args.cases.split(",") if args.cases else list(CASES)
    for name in names:
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
    with tempfile.TemporaryDirectory() as tmp:
        shared = Path(tmp) / "checkpoint"
        build_info = build_tiny_checkpoint(shared)
        for name in names:
            d = run_case(name, CASES[name], out, shared, build_info)
            print(f"wrote {d}")


# ----------------------------------------------------------------------------------------------
# Full-size random checkpoint (benchmarks)

FULL_IMAGE = {
    "shortest_image_edge": 256,
    "crop_fraction": 0.95,
    "image_target_size": [256, 256],
    "image_crop_size": [230, 230],
}
FULL_EMBODIMENTS = {
    "new_embodiment": dict(
        index=10,  # lerobot's N1_7_EMBODIMENT_MAPPING row for this tag
        video=["front"],
        state=[("arm", 6), ("gripper", 1)],
        action=[("arm", 6), ("gripper", 1)],
        action_types=["NON_EEF", "NON_EEF"],
        enum_case="upper",
        language="annotation.human.task_description",
        degenerate={},
        horizon=16,
        seed=47,
    ),
}
FULL_SHARD_BYTES = 2 * 1024**3
TIED = {"backbone.model.lm_head.weight": "backbone.model.model.language_model.embed_tokens.weight"}


def full_config():
    from lerobot.policies.groot.groot_n1_7 import GR00TN17Config

    cfg = GR00TN17Config(
        image_target_size=FULL_IMAGE["image_target_size"],
        image_crop_size=FULL_IMAGE["image_crop_size"],
        shortest_image_edge=FULL_IMAGE["shortest_image_edge"],
        crop_fraction=FULL_IMAGE["crop_fraction"],
    )
    cfg.architectures = ["GR00TN17"]  # what save_pretrained writes for the tiny checkpoints
    return cfg


def meta_model(cfg):
    """Upstream's network for `cfg` on the meta device (nothing allocated; lerobot's hard-coded Cosmos-Reason2-2B
    backbone config, so no hub access)."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17

    with torch.device("meta"), contextlib.redirect_stderr(io.StringIO()):
        return GR00TN17(cfg, load_backbone_weights=False)


def saved_layout(model) -> dict[str, tuple[tuple[int, ...], str]]:
    """Tensor names and shapes upstream's save_pretrained writes (the tied lm_head is left out)."""
    return {k: tuple(v.shape) for k, v in model.state_dict().items() if k not in TIED}


def check_full_size(out: Path) -> int:
    """The written shards against the network upstream builds from the written config.json: the same tensor
    names and shapes, all bfloat16, and an index that names every tensor."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17Config
    from safetensors import safe_open

    cfg = GR00TN17Config.from_pretrained(str(out))
    want = saved_layout(meta_model(cfg))
    index = json.loads((out / "model.safetensors.index.json").read_text())
    have: dict[str, tuple] = {}
    for shard in sorted(set(index["weight_map"].values())):
        with safe_open(str(out / shard), "pt") as f:
            for k in f.keys():
                sl = f.get_slice(k)
                have[k] = (tuple(sl.get_shape()), sl.get_dtype())
                if index["weight_map"][k] != shard:
                    raise RuntimeError(f"{k} is in {shard}, the index says {index['weight_map'][k]}")
    if set(want) != set(have):
        raise RuntimeError(f"names differ: {sorted(set(want) ^ set(have))[:10]}")
    for k, shape in want.items():
        if have[k] != (shape, "BF16"):
            raise RuntimeError(f"{k}: file {have[k]}, upstream {shape} BF16")
    n = sum(int(np.prod(s)) for s in want.values())
    print(f"checked {out}: {len(have)} tensors, {n} parameters, match upstream's GR00TN17 for its config.json")
    return n


def load_full_size(out: Path) -> None:
    """GR00TN17.from_pretrained on the checkpoint (bfloat16, as upstream loads it before lerobot's float32 cast;
    about 6.5 GB) and a tensor-by-tensor comparison with the shards."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17
    from safetensors import safe_open

    started = time.time()
    with contextlib.redirect_stderr(io.StringIO()):
        model = GR00TN17.from_pretrained(str(out.resolve()))
    state = model.state_dict()
    index = json.loads((out / "model.safetensors.index.json").read_text())
    for shard in sorted(set(index["weight_map"].values())):
        with safe_open(str(out / shard), "pt") as f:
            for k in f.keys():
                if not torch.equal(state[k], f.get_tensor(k)):
                    raise RuntimeError(f"{k} differs after loading")
    missing = [k for k in state if k not in index["weight_map"] and k not in TIED]
    if missing:
        raise RuntimeError(f"not in the shards: {missing[:8]}")
    dtypes = sorted({str(p.dtype) for p in model.parameters()})
    print(f"loaded {out} with GR00TN17.from_pretrained in {time.time() - started:.0f} s: every tensor equals the "
          f"shards (parameter dtypes {dtypes})")


def cmd_full_size(args) -> None:
    from safetensors.torch import save_file

    out = Path(args.out or CACHE / "checkpoints" / "gr00t_n17-full-random")
    if args.check_only:
        check_full_size(out)
        if args.load:
            load_full_size(out)
        return
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    started = time.time()
    ensure_full_hub()
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    cfg = full_config()
    model = meta_model(cfg)
    layout = saved_layout(model)
    gen = torch.Generator().manual_seed(5)
    names = list(layout)
    shards: list[list[str]] = [[]]
    size = 0
    for name in names:
        nbytes = int(np.prod(layout[name])) * 2
        if shards[-1] and size + nbytes > FULL_SHARD_BYTES:
            shards.append([])
            size = 0
        shards[-1].append(name)
        size += nbytes
    weight_map: dict[str, str] = {}
    total_bytes = total_params = 0
    for i, group in enumerate(shards):
        fname = f"model-{i + 1:05d}-of-{len(shards):05d}.safetensors"
        tensors = {}
        for name in group:
            tensors[name] = init_value(model, name, gen)[0].to(torch.bfloat16)
            weight_map[name] = fname
            total_params += tensors[name].numel()
            total_bytes += tensors[name].numel() * 2
        save_file(tensors, str(out / fname), metadata={"format": "pt"})
        (out / fname).chmod(0o644)
        del tensors
        print(f"wrote {fname} ({len(group)} tensors, {time.time() - started:.0f} s)")
    index = {
        "metadata": {"total_parameters": total_params, "total_size": total_bytes},
        "weight_map": dict(sorted(weight_map.items())),
    }
    (out / "model.safetensors.index.json").write_text(json.dumps(index, indent=2) + "\n")
    cfg.save_pretrained(str(out))
    write_sidecars(
        out, FULL_EMBODIMENTS, image=FULL_IMAGE, max_state_dim=cfg.max_state_dim, max_action_dim=cfg.max_action_dim,
        model_name=cfg.model_name, horizon=40,
    )
    elapsed = time.time() - started
    (out / "README.md").write_text(
        "Random-weight GR00T N1.7 checkpoint with the real sizes (lerobot's GR00T_N1_7_DEFAULTS: Cosmos-Reason2-2B "
        "backbone cut to 16 language layers, 32-block AlternateVLDiT, 4-layer VL self-attention), for benchmarks "
        "only.\n"
        f"Generated by `tools/oracle/run.sh gr00t_oracle.py full-size` in {elapsed:.0f} s: {total_params} parameters "
        f"in {len(shards)} bfloat16 shards (the tied lm_head is not stored, as upstream's save_pretrained leaves it "
        "out), every tensor drawn from a seeded normal (norm weights near 1, small biases, matrices scaled by "
        "1/sqrt(fan_in)).\n"
        "Embodiment `new_embodiment` (projector row 10), one camera `front` (frames of any size; 256x256 is "
        "typical), state and action groups arm (6) + gripper (1), 16 action steps, q01/q99 normalisation; "
        "processor_config.json: shortest_image_edge 256, crop_fraction 0.95, albumentations path.\n"
        "The Qwen3-VL processor files come from the stand-in `nvidia/Cosmos-Reason2-2B` in "
        "${TETHER_CACHE:-~/.cache/tether}/gr00t_hub (`gr00t_oracle.py hub`; real Qwen special-token ids, "
        "vocabulary padded to 151643 entries); point HF_HUB_CACHE there to run lerobot on this checkpoint.\n"
    )
    print(json.dumps({"out": str(out), "params": total_params, "shards": len(shards), "seconds": round(elapsed, 1)}))
    del model
    check_full_size(out)
    if args.load:
        load_full_size(out)


def ensure_full_hub() -> None:
    repo = FULL_HUB_CACHE / ("models--" + FULL_REPO.replace("/", "--"))
    if (repo / "refs" / "main").exists():
        return
    full_tok = train_tokenizer(TINY_BASE_VOCAB, fill_to=REAL_BASE_VOCAB)
    files = backbone_files(
        full_tok, vocab_size=151936, text=FULL_TEXT, vision=FULL_VISION, min_pixels=QWEN3_VL_MIN_PIXELS
    )
    print(f"wrote {write_repo(FULL_HUB_CACHE, FULL_REPO, FULL_REVISION, files)}")


def main(argv: list[str] | None = None) -> None:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    h = sub.add_parser("hub")
    h.add_argument("--out", default=str(HUB_CACHE))
    h.add_argument("--full-out", default=str(FULL_HUB_CACHE))
    h.add_argument("--tiny-only", action="store_true", help="skip the real-size stand-in")
    f = sub.add_parser("fixtures")
    f.add_argument("--out", default="")
    f.add_argument("--cases", default="")
    fs = sub.add_parser("full-size")
    fs.add_argument("--out", default="")
    fs.add_argument("--check-only", action="store_true", help="only compare an existing checkpoint with upstream")
    fs.add_argument("--load", action="store_true", help="also load it with GR00TN17.from_pretrained (about 6.5 GB)")
    args = p.parse_args(argv)
    logging.getLogger("lerobot").setLevel(logging.ERROR)
    {"hub": cmd_hub, "fixtures": cmd_fixtures, "full-size": cmd_full_size}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
