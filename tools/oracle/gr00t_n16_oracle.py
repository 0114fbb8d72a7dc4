"""Writes a tiny GR00T N1.6 checkpoint in NVIDIA's raw on-disk layout and records N1.6 block by block.

Usage:
  gr00t_n16_oracle.py [fixtures] [--out DIR]          the tiny fixtures (default tests/fixtures/gr00t_n16)
  gr00t_n16_oracle.py full-size [--out DIR] [--check-only]
                      random-weight checkpoint with the real N1.6 sizes in bfloat16 shards + index, and an Eagle
                      directory with the real sizes and token ids beside it (<out>/nvidia/Eagle-Block2A-2B-v2), for
                      benchmarks, not committed; default ${TETHER_CACHE:-~/.cache/tether}/checkpoints/
                      gr00t_n16-full-random. Built on the meta device and written tensor by tensor (one seeded
                      generator), then checked against the network built on the meta device from the written
                      configs; --check-only runs only that check. 2,975,968,192 parameters (vision
                      427,680,704 incl. the unused pooling head, mlp1 13,644,800, Qwen3 16 layers + embeddings
                      1,116,018,688, action head 1,418,624,000), 1105 tensors in 3 shards, 5.95 GB; about 1.5
                      minutes and 3.6 GB peak RSS on 2 cores.

N1.6's reference (Isaac-GR00T's `Gr00tN1d6`) is not on PyPI, imports flash-attn and cannot run here, so the
oracle is assembled from upstream classes wherever they exist and restates the rest from the Isaac-GR00T source:

  ran upstream classes
    transformers 5.5.4  Siglip2VisionModel (vision tower, one image at a time, all-ones patch mask),
                        Qwen3Model (LLM cut to select_layer layers, fed inputs_embeds), the stand-in tokenizer
                        loaded with AutoTokenizer (Qwen2Tokenizer) and its Jinja chat template
    lerobot 0.6.1       GR00TN17ActionHead built with no VL self-attention and state history 1 (the N1.6 head:
                        vlln, AlternateVLDiT, CategorySpecificMLP / MultiEmbodimentActionEncoder, 4-step sampler,
                        called through its own get_action), and its cv2 restatement of Isaac-GR00T's
                        albumentations eval geometry (_transform_n1_7_image_for_vlm_albumentations)
  restated from Isaac-GR00T (file and commit in each oracle's metadata)
    the Eagle glue (pixel-unshuffle x2 + mlp1, splicing image rows at <IMG_CONTEXT>, hidden_states[-1]),
    the Eagle processor (smart_resize factor 28 + PIL resize, fused rescale/normalise, <image-k> expansion),
    Gr00tN1d6Processor's language formalisation and StateActionProcessor's normalisation / decoding.

Weights are drawn from one seeded generator, rounded to bfloat16 and written as bf16 shards (the release dtype);
every recorded run uses their float32 upcast, in float32, on CPU with one thread, so two runs give byte-identical
files. The flow-matching noise is drawn inside the sampler with torch.randn; the oracle replaces torch.randn only
for that one call (gr00t_oracle.injected_noise) and hands back a seeded tensor, recorded as input.noise.

Outputs (see tests/fixtures/gr00t_n16/README.md): checkpoint/ (config.json, index + shards, processor_config.json,
statistics.json, embodiment_id.json), eagle/ (stand-in for the vendored Eagle-Block2A-2B-v2 directory: tiny
config.json, tokenizer files, chat template, image processor config), blocks/<block>/oracle.safetensors and
cases/<case>/{inputs/*.png, oracle.safetensors}.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import math
import os
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from gr00t_oracle import (
    CORPUS,
    QWEN3_VL_ADDED,
    TINY_BASE_VOCAB,
    decode_png,
    draw_frame,
    dump_json,
    group_stats,
    init_value,
    injected_noise,
    tokenizer_json,
    train_tokenizer,
    versions,
)
from smolvla_oracle import write_safetensors

REPO_ROOT = Path(__file__).resolve().parents[2]
GENERATOR = "tools/oracle/run.sh gr00t_n16_oracle.py"

# ----------------------------------------------------------------------------------------------
# Upstream sources read for the restated parts (NVIDIA/Isaac-GR00T; path -> commit of the stored version read)

ISAAC = {
    "gr00t/model/gr00t_n1d6/gr00t_n1d6.py": "55879c297db64f3a4c4fc3440363a8aef1e16ca2",
    "gr00t/model/modules/eagle_backbone.py": "37e36ef3a4299c508f20b5757dbd18cf6a380eda",
    "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/modeling_eagle3_vl.py": "77988d1a07ead06c75046856336c5c8282ec1b07",
    "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/modeling_siglip2.py": "0c8fb7d52a89f9bcb4369053813315df647533c2",
    "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/configuration_eagle3_vl.py":
        "ade260e6d08b629dad7cea33910113efc2e6752a",
    "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/processing_eagle3_vl.py":
        "971877927283dfdc17a9c8c1e2284354c6f31121",
    "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/image_processing_eagle3_vl_fast.py":
        "971877927283dfdc17a9c8c1e2284354c6f31121",
    "gr00t/model/gr00t_n1d6/processing_gr00t_n1d6.py": "005e8a4f719383fb0bc6af5a64e72bb87ca04fc2",
    "gr00t/model/gr00t_n1d6/image_augmentations.py": "2ce75434d3b926d5d08af9b27f2df5cd060f4db5",
    "gr00t/data/state_action/state_action_processor.py": "98a45fe6604c96ff2244750473aeee6efb43b08b",
    "gr00t/configs/model/gr00t_n1d6.py": "9b37aa1ce69c73c6d165233fa88128283bba4508",
}


def src(*paths: str) -> list[str]:
    return [f"NVIDIA/Isaac-GR00T:{p}@{ISAAC[p]}" for p in paths]


# ----------------------------------------------------------------------------------------------
# Tiny sizes

SEED = 23
PATCH = 14
SIGLIP2 = dict(
    hidden_size=32,
    intermediate_size=64,
    num_hidden_layers=2,
    num_attention_heads=2,
    num_channels=3,
    num_patches=16,  # a 4x4 learned position table (the release: 256 = 16x16)
    patch_size=PATCH,
    hidden_act="gelu_pytorch_tanh",
    layer_norm_eps=1e-6,
    attention_dropout=0.0,
)
QWEN3 = dict(
    hidden_size=64,
    intermediate_size=128,
    num_hidden_layers=4,  # as the backbone config has it; GR00T keeps select_layer of them
    num_attention_heads=4,
    num_key_value_heads=2,
    head_dim=16,
    hidden_act="silu",
    rms_norm_eps=1e-6,
    rope_theta=1000000.0,
    max_position_embeddings=4096,
    attention_bias=False,
    tie_word_embeddings=True,
)
SELECT_LAYER = 3
VOCAB_SIZE = 576  # embedding rows; the tokenizer has 512 + 26 + 3 = 541 entries
EAGLE_ADDED = ["<IMG_CONTEXT>", "<img>", "</img>"]  # after Qwen3's 26 added tokens, as 151669 / 151670 / 151671
DOWNSAMPLE = 0.5
PIXELS_PER_TOKEN = 28 * 28
MODEL_HORIZON = 8
MAX_DIM = 16
NUM_EMBODIMENTS = 32
HEAD = dict(
    backbone_embedding_dim=QWEN3["hidden_size"],
    hidden_size=32,
    input_embedding_dim=32,
    max_state_dim=MAX_DIM,
    max_action_dim=MAX_DIM,
    action_horizon=MODEL_HORIZON,
    max_num_embodiments=NUM_EMBODIMENTS,
    max_seq_len=16,
    add_pos_embed=True,
    use_vlln=True,
    use_alternate_vl_dit=True,
    attend_text_every_n_blocks=2,
    attn_dropout=0.2,
    diffusion_model_cfg={
        "positional_embeddings": None,
        "num_layers": 4,
        "num_attention_heads": 4,
        "attention_head_dim": 8,
        "norm_type": "ada_norm",
        "dropout": 0.2,
        "final_dropout": True,
        "output_dim": 32,
        "interleave_self_attention": True,
    },
    num_inference_timesteps=4,
    noise_beta_alpha=1.5,
    noise_beta_beta=1.0,
    noise_s=0.999,
    num_timestep_buckets=1000,
    state_dropout_prob=0.0,
)
IMAGE = {"shortest_image_edge": 56, "crop_fraction": 0.95}
# smart_resize constants of processing_eagle3_vl.py
IMAGE_FACTOR = 28
MIN_PIXELS = 4 * 28 * 28
MAX_PIXELS = 4096 * 28 * 28
MAX_RATIO = 200
IMAGE_MAX_SIZE = 500 * 14

# EMBODIMENT_TAG_TO_PROJECTOR_INDEX of processing_gr00t_n1d6.py; save_pretrained writes the whole mapping
N16_EMBODIMENT_IDS = {
    "robocasa_panda_omron": 13,
    "gr1": 20,
    "behavior_r1_pro": 24,
    "unitree_g1": 8,
    "libero_panda": 2,
    "oxe_google": 0,
    "oxe_widowx": 1,
    "oxe_droid": 16,
    "new_embodiment": 10,
}

EMBODIMENTS = {
    # one camera; state: a min/max group, a sin/cos group and a mean/std group (with a std == 0 dimension)
    "libero_panda": dict(
        video=["image"],
        state=[("eef_pos", 3), ("eef_rot", 3), ("gripper", 2)],
        sin_cos=["eef_rot"],
        mean_std=["gripper"],
        action=[("eef_pos", 3), ("eef_rot", 3), ("gripper", 1)],
        action_types=["EEF", "EEF", "NON_EEF"],
        language="annotation.human.action.task_description",
        horizon=6,
        degenerate={"state": ("gripper", 1), "action": ("eef_rot", 2)},
        seed=61,
    ),
    # two cameras; state: a min/max arm with a degenerate dimension, a min/max gripper, a sin/cos base yaw
    "new_embodiment": dict(
        video=["front", "wrist"],
        state=[("arm", 6), ("gripper", 1), ("base_yaw", 1)],
        sin_cos=["base_yaw"],
        mean_std=[],
        action=[("arm", 6), ("gripper", 1)],
        action_types=["NON_EEF", "NON_EEF"],
        language="annotation.human.task_description",
        horizon=MODEL_HORIZON,
        degenerate={"state": ("arm", 4)},
        seed=67,
    ),
}


# ----------------------------------------------------------------------------------------------
# Stand-in tokenizer (the vendored Eagle-Block2A-2B-v2 tokenizer: Qwen3's, plus the Eagle tokens)

# Rendering of the default-system-message chat format of docs/design/gr00t.md 5.2 (the vendored
# chat_template.json itself was not in the record this script was written from): text items verbatim,
# image items as <image-k> (k counted from 1 over the conversation), no generation prompt.
CHAT_TEMPLATE = (
    "{%- set image_count = namespace(value=0) -%}"
    "{%- for message in messages -%}"
    "{%- if loop.first and message['role'] != 'system' -%}"
    "{{- '<|im_start|>system\\nYou are a helpful assistant.<|im_end|>\\n' -}}"
    "{%- endif -%}"
    "{{- '<|im_start|>' + message['role'] + '\\n' -}}"
    "{%- if message['content'] is string -%}"
    "{{- message['content'] -}}"
    "{%- else -%}"
    "{%- for item in message['content'] -%}"
    "{%- if item['type'] == 'image' or 'image' in item -%}"
    "{%- set image_count.value = image_count.value + 1 -%}"
    "{{- '<image-' + image_count.value|string + '>' -}}"
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


def build_tokenizer(fill_to: int | None = None):
    """The trained 512-entry BPE + Qwen3's 26 added tokens + the Eagle tokens; `fill_to` pads the base vocabulary
    (gr00t_oracle.train_tokenizer) so the added tokens land on the real ids (151643 -> <|endoftext|> 151643, ...,
    <IMG_CONTEXT> 151669)."""
    from tokenizers import AddedToken

    tok = train_tokenizer(TINY_BASE_VOCAB, fill_to)
    first = tok.get_vocab_size()
    for i, content in enumerate(EAGLE_ADDED):
        tok.add_special_tokens([AddedToken(content, special=True, normalized=False, lstrip=False, rstrip=False)])
        if tok.token_to_id(content) != first + i:
            raise RuntimeError(f"{content} got id {tok.token_to_id(content)}")
    return tok


def added_list():
    return [(c, s) for c, s in QWEN3_VL_ADDED] + [(c, True) for c in EAGLE_ADDED]


def write_eagle_dir(d: Path, tok, *, vision: dict = SIGLIP2, text: dict = QWEN3,
                    vocab_size: int = VOCAB_SIZE) -> dict[str, int]:
    """The stand-in for gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/: tokenizer files as a Qwen2Tokenizer
    directory has them (vocab.json, merges.txt, added_tokens.json, tokenizer_config.json, special_tokens_map.json)
    plus tokenizer.json, chat_template.json, the Eagle3 image processor and processor configs, and the tiny
    Eagle3_VLConfig (config.json; the full-size command passes the real sizes)."""
    from tokenizers import Tokenizer

    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    data = json.loads(tok.to_str())
    vocab = data["model"]["vocab"]
    (d / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False, separators=(",", ":")) + "\n")
    merges = data["model"]["merges"]
    lines = ["#version: 0.2"] + [" ".join(m) if isinstance(m, list) else m for m in merges]
    (d / "merges.txt").write_text("\n".join(lines) + "\n")
    ids = {c: tok.token_to_id(c) for c, _ in added_list()}
    (d / "added_tokens.json").write_text(dump_json(ids))
    (d / "tokenizer.json").write_text(tokenizer_json(tok))
    decoder = {
        str(ids[c]): {"content": c, "lstrip": False, "normalized": False, "rstrip": False, "single_word": False,
                      "special": s}
        for c, s in added_list()
    }
    specials = [c for c, s in added_list() if s and c != "<|endoftext|>"]
    tcfg = {
        "add_bos_token": False,
        "add_prefix_space": False,
        "added_tokens_decoder": decoder,
        "additional_special_tokens": specials,
        "bos_token": None,
        "chat_template": CHAT_TEMPLATE,
        "clean_up_tokenization_spaces": False,
        "eos_token": "<|im_end|>",
        "errors": "replace",
        "model_max_length": 131072,
        "pad_token": "<|endoftext|>",
        "padding_side": "left",
        "split_special_tokens": False,
        "tokenizer_class": "Qwen2Tokenizer",
        "unk_token": None,
    }
    (d / "tokenizer_config.json").write_text(dump_json(tcfg))
    (d / "special_tokens_map.json").write_text(dump_json({
        "additional_special_tokens": specials, "eos_token": "<|im_end|>", "pad_token": "<|endoftext|>",
    }))
    (d / "chat_template.json").write_text(dump_json({"chat_template": CHAT_TEMPLATE}))
    (d / "preprocessor_config.json").write_text(dump_json({
        "do_convert_rgb": True,
        "do_normalize": True,
        "do_pad": False,
        "do_rescale": True,
        "do_resize": False,
        "image_mean": [0.5, 0.5, 0.5],
        "image_processor_type": "Eagle3_VLImageProcessorFast",
        "image_std": [0.5, 0.5, 0.5],
        "processor_class": "Eagle3_VLProcessor",
        "resample": 3,
        "rescale_factor": 1 / 255,
    }))
    (d / "processor_config.json").write_text(dump_json({
        "image_end_token": "</img>",
        "image_placeholder": "image",
        "image_start_token": "<img>",
        "image_token": "<IMG_CONTEXT>",
        "pixels_per_token": PIXELS_PER_TOKEN,
        "processor_class": "Eagle3_VLProcessor",
        "video_placeholder": "video",
        "video_token": "<IMG_CONTEXT>",
    }))
    (d / "config.json").write_text(dump_json(eagle_config(ids, vision=vision, text=text, vocab_size=vocab_size)))
    # the vocab.json / merges.txt pair must rebuild the same tokenizer as tokenizer.json
    from tokenizers import models

    rebuilt = Tokenizer.from_str(tok.to_str())
    rebuilt.model = models.BPE.from_file(str(d / "vocab.json"), str(d / "merges.txt"))
    for text in CORPUS[:8]:
        if rebuilt.encode(text).ids != tok.encode(text).ids:
            raise RuntimeError("vocab.json/merges.txt rebuild differs from tokenizer.json")
    return ids


def eagle_config(ids: dict[str, int], *, vision: dict = SIGLIP2, text: dict = QWEN3,
                 vocab_size: int = VOCAB_SIZE) -> dict:
    """Eagle3_VLConfig (configuration_eagle3_vl.py) with the given SigLIP2 / Qwen3 sizes (default the tiny ones)."""
    vision = dict(vision, model_type="siglip2_vision_model", use_rope=False, use_windows_attn=False,
                  window_size=14, full_attention_indexes=[], vision_use_head=True)
    text = dict(text, architectures=["Qwen3ForCausalLM"], model_type="qwen3", vocab_size=vocab_size,
                bos_token_id=ids["<|endoftext|>"], eos_token_id=ids["<|im_end|>"], use_cache=False,
                attention_dropout=0.0, initializer_range=0.02, use_sliding_window=False)
    return {
        "architectures": ["Eagle3_VLForConditionalGeneration"],
        "downsample_ratio": DOWNSAMPLE,
        "image_token_index": ids["<IMG_CONTEXT>"],
        "loss_version": "v4",
        "mlp_checkpoint": False,
        "model_type": "eagle_3_vl",
        "select_layer": -1,
        "template": "qwen3-chat",
        "text_config": text,
        "torch_dtype": "bfloat16",
        "use_backbone_lora": 0,
        "use_llm_lora": 0,
        "vision_config": vision,
    }


# ----------------------------------------------------------------------------------------------
# The tiny network: upstream modules under N1.6's parameter names


class TinyN16(torch.nn.Module):
    """backbone.model.{vision_model (transformers Siglip2VisionModel), mlp1, language_model.model (transformers
    Qwen3Model, select_layer layers)} + action_head (lerobot GR00TN17ActionHead without VL self-attention).
    Tiny sizes by default; the full-size command builds it with the real ones on the meta device."""

    def __init__(self, *, vision: dict = SIGLIP2, text: dict = QWEN3, select_layer: int = SELECT_LAYER,
                 vocab_size: int = VOCAB_SIZE, head: dict = HEAD):
        super().__init__()
        from lerobot.policies.groot.groot_n1_7 import GR00TN17ActionHead, GR00TN17Config
        from transformers import Qwen3Config, Qwen3Model, Siglip2VisionConfig, Siglip2VisionModel

        vcfg = Siglip2VisionConfig(**vision)
        vcfg._attn_implementation = "eager"
        tcfg = Qwen3Config(**dict(text, num_hidden_layers=select_layer), vocab_size=vocab_size)
        tcfg._attn_implementation = "eager"
        self.backbone = torch.nn.Module()
        self.backbone.model = torch.nn.Module()
        bm = self.backbone.model
        bm.vision_model = Siglip2VisionModel(vcfg)
        width = vision["hidden_size"] * int(1 / DOWNSAMPLE) ** 2
        bm.mlp1 = torch.nn.Sequential(
            torch.nn.LayerNorm(width),
            torch.nn.Linear(width, text["hidden_size"]),
            torch.nn.GELU(),
            torch.nn.Linear(text["hidden_size"], text["hidden_size"]),
        )
        bm.language_model = torch.nn.Module()
        bm.language_model.model = Qwen3Model(tcfg)
        hcfg = GR00TN17Config(**head, state_history_length=1,
                              vl_self_attention_cfg={"num_layers": 0})
        with contextlib.redirect_stdout(io.StringIO()):
            self.action_head = GR00TN17ActionHead(hcfg)
        if not isinstance(self.action_head.vl_self_attention, torch.nn.Identity):
            raise RuntimeError("VL self-attention was built")

    @property
    def vision(self):
        return self.backbone.model.vision_model

    @property
    def mlp1(self):
        return self.backbone.model.mlp1

    @property
    def llm(self):
        return self.backbone.model.language_model.model


def randomize(model: torch.nn.Module, seed: int) -> dict:
    """gr00t_oracle.init_value for every parameter in named_parameters order (one generator); the SigLIP2
    pooling head's packed nn.MultiheadAttention bias (in_proj_bias) is drawn as a bias."""
    gen = torch.Generator().manual_seed(seed)
    rules: dict[str, int] = {}
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("in_proj_bias"):
                value, rule = torch.randn(tuple(p.shape), generator=gen).mul_(0.05), "bias"
            else:
                value, rule = init_value(model, name, gen)
            p.copy_(value.to(torch.bfloat16).float())
            rules[rule] = rules.get(rule, 0) + 1
    return rules


def gr00t_config_json(head: dict = HEAD, select_layer: int = SELECT_LAYER, image: dict = IMAGE) -> dict:
    """config.json with every Gr00tN1d6Config field (gr00t/configs/model/gr00t_n1d6.py), tiny values by default."""
    cfg = {
        "architectures": ["Gr00tN1d6"],
        "model_type": "Gr00tN1d6",
        "model_dtype": "bfloat16",
        "torch_dtype": "bfloat16",
        "transformers_version": "4.51.3",
        "model_name": "nvidia/Eagle-Block2A-2B-v2",
        "backbone_model_type": "eagle",
        "model_revision": None,
        "tune_top_llm_layers": 4,
        "backbone_embedding_dim": head["backbone_embedding_dim"],
        "tune_llm": False,
        "tune_visual": False,
        "select_layer": select_layer,
        "reproject_vision": False,
        "use_flash_attention": True,
        "load_bf16": True,
        "collator_overwrite_image_inputs": False,
        "eagle_collator": False,
        "backbone_trainable_params_fp32": True,
        "image_crop_size": None,
        "image_target_size": None,
        "shortest_image_edge": image["shortest_image_edge"],
        "crop_fraction": image["crop_fraction"],
        "random_rotation_angle": None,
        "color_jitter_params": None,
        "use_albumentations_transforms": True,
        "letter_box_transform": False,
        "extra_augmentation_config": None,
        "formalize_language": True,
        "apply_sincos_state_encoding": True,
        "use_relative_action": False,
        "tune_projector": True,
        "tune_diffusion_model": True,
        "tune_vlln": True,
        "state_additive_noise_scale": 0.0,
    }
    cfg.update({k: v for k, v in head.items()})
    return dict(sorted(cfg.items()))


def shard_and_write(ckpt: Path, state: dict[str, torch.Tensor], max_bytes: int) -> list[str]:
    """bf16 shards in state_dict order, split before a tensor that would overflow max_bytes, named
    model-0000k-of-0000n.safetensors, and model.safetensors.index.json (metadata total_size, weight_map)."""
    groups: list[list[str]] = [[]]
    size = 0
    for name, t in state.items():
        nbytes = t.numel() * 2
        if groups[-1] and size + nbytes > max_bytes:
            groups.append([])
            size = 0
        groups[-1].append(name)
        size += nbytes
    n = len(groups)
    weight_map, files, total = {}, [], 0
    for k, names in enumerate(groups, start=1):
        fname = f"model-{k:05d}-of-{n:05d}.safetensors"
        write_safetensors(ckpt / fname, {nm: state[nm].to(torch.bfloat16) for nm in names}, {"format": "pt"})
        files.append(fname)
        for nm in names:
            weight_map[nm] = fname
            total += state[nm].numel() * 2
    (ckpt / "model.safetensors.index.json").write_text(
        json.dumps({"metadata": {"total_size": total}, "weight_map": dict(sorted(weight_map.items()))}, indent=2)
        + "\n"
    )
    return files


def embodiment_statistics(emb: dict) -> dict:
    gen = np.random.default_rng(emb["seed"])
    out: dict = {"state": {}, "action": {}, "relative_action": {}}
    for modality in ("state", "action"):
        deg = emb["degenerate"].get(modality)
        for key, dim in emb[modality]:
            out[modality][key] = group_stats(gen, dim, deg[1] if deg and deg[0] == key else None)
    return out


def modality_config(emb: dict) -> dict:
    def entry(delta, keys, sin_cos=None, mean_std=None, action_configs=None):
        return {"delta_indices": delta, "modality_keys": keys, "sin_cos_embedding_keys": sin_cos,
                "mean_std_embedding_keys": mean_std, "action_configs": action_configs}

    return {
        "video": entry([0], list(emb["video"])),
        "state": entry([0], [k for k, _ in emb["state"]], emb["sin_cos"] or None, emb["mean_std"] or None),
        "action": entry(
            list(range(emb["horizon"])), [k for k, _ in emb["action"]],
            action_configs=[{"rep": "ABSOLUTE", "type": t, "format": "DEFAULT", "state_key": None}
                            for t in emb["action_types"]],
        ),
        "language": entry([0], [emb["language"]]),
    }


def processor_config(embodiments: dict = EMBODIMENTS, image: dict = IMAGE, max_dim: int = MAX_DIM,
                     horizon: int = MODEL_HORIZON) -> dict:
    """processor_config.json as Gr00tN1d6Processor.save_pretrained lays it out."""
    return {
        "processor_class": "Gr00tN1d6Processor",
        "processor_kwargs": {
            "modality_configs": {tag: modality_config(e) for tag, e in embodiments.items()},
            "image_crop_size": None,
            "image_target_size": None,
            "use_albumentations": True,
            "random_rotation_angle": None,
            "color_jitter_params": None,
            "shortest_image_edge": image["shortest_image_edge"],
            "crop_fraction": image["crop_fraction"],
            "model_name": "nvidia/Eagle-Block2A-2B-v2",
            "model_type": "eagle",
            "formalize_language": True,
            "max_state_dim": max_dim,
            "max_action_dim": max_dim,
            "max_action_horizon": horizon,
            "use_percentiles": False,
            "clip_outliers": True,
            "apply_sincos_state_encoding": True,
            "use_relative_action": False,
        },
    }


def build_checkpoint(ckpt: Path) -> tuple[TinyN16, dict]:
    if ckpt.exists():
        shutil.rmtree(ckpt)
    ckpt.mkdir(parents=True)
    torch.manual_seed(SEED)
    model = TinyN16()
    rules = randomize(model, SEED)
    model.eval()
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    # non-persistent buffers (rotary inv_freq) are not in state_dict; the release stores parameters only
    files = shard_and_write(ckpt, state, 400 * 1024)
    (ckpt / "config.json").write_text(json.dumps(gr00t_config_json(), indent=2) + "\n")
    (ckpt / "processor_config.json").write_text(json.dumps(processor_config(), indent=2) + "\n")
    (ckpt / "statistics.json").write_text(
        json.dumps({tag: embodiment_statistics(e) for tag, e in EMBODIMENTS.items()}, indent=2) + "\n"
    )
    (ckpt / "embodiment_id.json").write_text(json.dumps(N16_EMBODIMENT_IDS, indent=2) + "\n")
    # reload: the shards hold exactly the model's parameters, in bf16, and the float32 upcast is what runs
    from safetensors.torch import load_file

    loaded: dict[str, torch.Tensor] = {}
    for f in files:
        loaded.update(load_file(str(ckpt / f)))
    if set(loaded) != set(state):
        raise RuntimeError("shards and model differ in names")
    for k, v in loaded.items():
        if v.dtype != torch.bfloat16 or not torch.equal(v.float(), state[k]):
            raise RuntimeError(f"{k} changed through the bf16 shards")
    model.load_state_dict({k: v.float() for k, v in loaded.items()}, strict=True)
    info = {
        "init_rules": rules,
        "shards": files,
        "tensors": len(state),
        "parameters": sum(p.numel() for p in model.parameters()),
    }
    return model, info


# ----------------------------------------------------------------------------------------------
# Restated pieces (Eagle glue and processors)


def smart_resize(height: int, width: int, factor: int = IMAGE_FACTOR, min_pixels: int = MIN_PIXELS,
                 max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """processing_eagle3_vl.smart_resize: Python round to multiples of factor, clamp to [factor, 7000], then the
    max_pixels branch (floor of h_bar/beta) or the min_pixels branch (ceil of height*beta, from the ORIGINAL
    size)."""
    if max(height, width) / min(height, width) > MAX_RATIO:
        raise ValueError("aspect ratio")
    h_bar = min(max(factor, round(height / factor) * factor), IMAGE_MAX_SIZE)
    w_bar = min(max(factor, round(width / factor) * factor), IMAGE_MAX_SIZE)
    if h_bar * w_bar > max_pixels:
        beta = math.sqrt((h_bar * w_bar) / max_pixels)
        h_bar = math.floor(h_bar / beta / factor) * factor
        w_bar = math.floor(w_bar / beta / factor) * factor
    elif h_bar * w_bar < min_pixels:
        beta = math.sqrt(min_pixels / (height * width))
        h_bar = math.ceil(height * beta / factor) * factor
        w_bar = math.ceil(width * beta / factor) * factor
    return h_bar, w_bar


def fetch_image(arr: np.ndarray) -> np.ndarray:
    """processing_eagle3_vl.fetch_image for a PIL image: convert("RGB"), smart_resize, Image.resize((w, h)) with
    Pillow's default filter (bicubic; a same-size resize is a copy)."""
    im = Image.fromarray(arr, "RGB").convert("RGB")
    w, h = im.size
    rh, rw = smart_resize(h, w)
    return np.asarray(im.resize((rw, rh)), dtype=np.uint8).copy()


def eagle_pixel_values(arr: np.ndarray) -> torch.Tensor:
    """Eagle3_VLImageProcessorFast: no resize; transformers 4.51.3 BaseImageProcessorFast fuses rescale (1/255)
    and normalise (mean 0.5, std 0.5) into mean' = 0.5 * 255 = 127.5, std' = 127.5 and computes
    (x - 127.5) / 127.5 in float32 (torchvision normalize). Returns [1, 3, H, W]."""
    x = torch.from_numpy(arr).permute(2, 0, 1).contiguous().to(torch.float32)
    mean = torch.tensor([0.5] * 3) * (1.0 / (1 / 255))
    std = torch.tensor([0.5] * 3) * (1.0 / (1 / 255))
    return ((x - mean[:, None, None]) / std[:, None, None]).unsqueeze(0)


def patchify(pixel_values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[1, 3, H, W] -> SigLIP2 patches [1, (H/14)(W/14), 588] in (py, px, c) order, with transformers'
    image_processing_siglip2.convert_image_to_patches (Eagle's convert_images_to_patches has the same order)."""
    from transformers.models.siglip2.image_processing_siglip2 import convert_image_to_patches

    _, _, h, w = pixel_values.shape
    patches = convert_image_to_patches(pixel_values[0], PATCH).unsqueeze(0).contiguous()
    return patches, torch.tensor([[h // PATCH, w // PATCH]], dtype=torch.int64)


def run_vision(model: TinyN16, pixel_values: torch.Tensor, rec: dict, prefix: str) -> torch.Tensor:
    """Siglip2VisionModel on one image; records patches, spatial shape, resized position table, embeddings after
    the position add, each encoder layer's output and last_hidden_state (after post_layernorm)."""
    vt = model.vision.vision_model
    patches, shapes = patchify(pixel_values)
    n = patches.shape[1]
    caught: dict[str, torch.Tensor] = {}
    hs = [
        vt.embeddings.register_forward_hook(lambda _m, _i, o: caught.__setitem__("emb", o.detach().clone())),
    ]
    for i, layer in enumerate(vt.encoder.layers):
        hs.append(layer.register_forward_hook(
            lambda _m, _i, o, i=i: caught.__setitem__(f"layer{i}", (o[0] if isinstance(o, tuple) else o).clone())))
    out = model.vision(pixel_values=patches, pixel_attention_mask=torch.ones(1, n, dtype=torch.int32),
                       spatial_shapes=shapes)
    for h in hs:
        h.remove()
    table = vt.embeddings.position_embedding.weight
    side = vt.embeddings.position_embedding_size
    pos = vt.embeddings.resize_positional_embeddings(table.reshape(side, side, -1), shapes, max_length=n)[0]
    rec[f"{prefix}.patches"] = patches
    rec[f"{prefix}.spatial_shapes"] = shapes
    rec[f"{prefix}.pos_embed"] = pos
    rec[f"{prefix}.embeddings"] = caught["emb"]
    if not torch.allclose(caught["emb"], vt.embeddings.patch_embedding(patches) + pos, atol=0, rtol=0):
        raise RuntimeError("embeddings != patch_embedding + resized table")
    for i in range(len(vt.encoder.layers)):
        rec[f"{prefix}.layer.{i}"] = caught[f"layer{i}"]
    rec[f"{prefix}.last_hidden_state"] = out.last_hidden_state
    return out.last_hidden_state


def run_projector(model: TinyN16, vit: torch.Tensor, hw: tuple[int, int], rec: dict | None, prefix: str):
    """Eagle3_VLForConditionalGeneration.pixel_shuffle_back + mlp1 for one image: [h*w, C] -> [C, h, w] ->
    F.pixel_unshuffle(., 2) -> [4C, h/2, w/2] (channel c*4 + dy*2 + dx) -> raster tokens [hw/4, 4C] -> mlp1."""
    h, w = hw
    if h % 2 or w % 2:
        raise ValueError(f"odd patch grid {h}x{w}: pixel_unshuffle needs even sides (smart_resize factor 28 "
                         "always gives even grids)")
    c = vit.shape[-1]
    grid = vit.reshape(-1, c).transpose(0, 1).reshape(c, h, w)
    un = torch.nn.functional.pixel_unshuffle(grid.unsqueeze(0), 2)[0]
    tokens = un.flatten(start_dim=1).transpose(0, 1).contiguous()
    m = model.mlp1
    ln = m[0](tokens)
    fc1 = m[1](ln)
    act = m[2](fc1)
    out = m[3](act)
    if not torch.equal(out, m(tokens)):
        raise RuntimeError("mlp1 stepwise != Sequential")
    if rec is not None:
        rec[f"{prefix}.unshuffled"] = tokens
        rec[f"{prefix}.mlp1.0"] = ln
        rec[f"{prefix}.mlp1.1"] = fc1
        rec[f"{prefix}.mlp1.2"] = act
        rec[f"{prefix}.out"] = out
    return out


def splice(model: TinyN16, input_ids: torch.Tensor, image_rows: torch.Tensor, image_token: int) -> torch.Tensor:
    """Eagle3_VLForConditionalGeneration.forward: token embeddings, rows at input_ids == <IMG_CONTEXT> replaced
    (x * 0.0 + vit, in batch-major raster order) by the projector rows of all images in order."""
    emb = model.llm.embed_tokens(input_ids)
    b, n, c = emb.shape
    flat = emb.reshape(b * n, c).clone()
    sel = input_ids.reshape(b * n) == image_token
    if int(sel.sum()) != image_rows.shape[0]:
        raise RuntimeError(f"{int(sel.sum())} image tokens, {image_rows.shape[0]} image rows")
    flat[sel] = flat[sel] * 0.0 + image_rows
    return flat.reshape(b, n, c)


def run_llm(model: TinyN16, embeds: torch.Tensor, mask: torch.Tensor, rec: dict | None, prefix: str):
    """Qwen3Model (select_layer layers) on inputs_embeds with the 2-D padding mask and no position ids (0..L-1 per
    row, as Eagle's forward passes position_ids=None); returns last_hidden_state, i.e. after the final RMSNorm,
    which is hidden_states[-1] (checked)."""
    out = model.llm(inputs_embeds=embeds, attention_mask=mask, output_hidden_states=True, use_cache=False)
    hs = out.hidden_states
    if len(hs) != SELECT_LAYER + 1 or not torch.equal(hs[-1], out.last_hidden_state):
        raise RuntimeError("hidden_states[-1] is not last_hidden_state")
    if rec is not None:
        if not torch.equal(hs[0], embeds):
            raise RuntimeError("hidden_states[0] is not inputs_embeds")
        for i in range(1, SELECT_LAYER):
            rec[f"{prefix}.hidden_states.{i}"] = hs[i]  # output of decoder layer i - 1 (0 is inputs_embeds)
        rec[f"{prefix}.last_layer_prenorm"] = pre_norm_output(model, embeds, mask)
        rec[f"{prefix}.last_hidden_state"] = out.last_hidden_state
    return out.last_hidden_state


def pre_norm_output(model: TinyN16, embeds, mask):
    caught = {}
    h = model.llm.layers[-1].register_forward_hook(
        lambda _m, _i, o: caught.__setitem__("x", (o[0] if isinstance(o, tuple) else o).clone()))
    model.llm(inputs_embeds=embeds, attention_mask=mask, use_cache=False)
    h.remove()
    return caught["x"]


def formalize(text: str) -> str:
    """Gr00tN1d6Processor.__call__ with formalize_language: lower(), then drop every char matching [^\\w\\s]."""
    return re.sub(r"[^\w\s]", "", text.lower())


def normalize_state(tag: str, raw: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """StateActionProcessor.apply_state with apply_sincos_state_encoding, use_percentiles false, clip_outliers:
    per group in modality_keys order: sin/cos keys -> [sin(x)..., cos(x)...] (numpy, the input's float32);
    mean/std keys -> (x - mean) / std where std != 0, x where std == 0; otherwise min/max -> 2 (x - min) /
    (max - min) - 1 where not np.isclose(max, min) (0 there), clipped to [-1, 1]. The output array has the input's
    dtype (float32; the division runs in float64 and is stored back to float32, then 2n - 1 runs in float32).
    Returns the concatenation padded with zeros to max_state_dim, and the per-group values."""
    emb = EMBODIMENTS[tag]
    stats = embodiment_statistics(emb)["state"]
    groups: dict[str, np.ndarray] = {}
    for key, _dim in emb["state"]:
        x = raw[key]
        st = {k: np.array(v) for k, v in stats[key].items()}
        if key in emb["sin_cos"]:
            y = np.concatenate([np.sin(x), np.cos(x)], axis=-1)
        elif key in emb["mean_std"]:
            y = np.zeros_like(x)
            m = st["std"] != 0
            y[..., m] = (x[..., m] - st["mean"][..., m]) / st["std"][..., m]
            y[..., ~m] = x[..., ~m]
        else:
            lo, hi = st["min"], st["max"]
            y = np.zeros_like(x)
            m = ~np.isclose(hi, lo)
            y[..., m] = (x[..., m] - lo[..., m]) / (hi[..., m] - lo[..., m])
            y[..., m] = 2 * y[..., m] - 1
            y = np.clip(y, -1.0, 1.0)
        groups[key] = y
    cat = np.concatenate([groups[k] for k, _ in emb["state"]], axis=-1)
    pad = np.concatenate([cat, np.zeros((cat.shape[0], MAX_DIM - cat.shape[1]), dtype=cat.dtype)], axis=-1)
    return pad.astype(np.float32), groups


def decode_actions(tag: str, action_pred: np.ndarray) -> dict[str, np.ndarray]:
    """Gr00tN1d6Processor.decode_action + StateActionProcessor.unapply_action (absolute, min/max): rows
    [0, len(action.delta_indices)), columns cut per group in modality_keys order (widths from the statistics),
    then (clip(n, -1, 1) + 1) / 2 * (max - min) + min (float32 input, float64 statistics -> float64)."""
    emb = EMBODIMENTS[tag]
    stats = embodiment_statistics(emb)["action"]
    out, start = {}, 0
    for key, dim in emb["action"]:
        n = action_pred[..., : emb["horizon"], start:start + dim]
        lo, hi = np.array(stats[key]["min"]), np.array(stats[key]["max"])
        out[key] = (np.clip(n, -1.0, 1.0) + 1.0) / 2.0 * (hi - lo) + lo
        start += dim
    return out


# ----------------------------------------------------------------------------------------------
# Recording helpers


class HeadProbes:
    def __init__(self, head):
        self.rec: dict[str, list] = {}
        self.handles = []

        def keep(name):
            def hook(_m, _i, out):
                self.rec.setdefault(name, []).append(out.detach().clone())
            return hook

        self.handles.append(head.vlln.register_forward_hook(keep("vlln")))
        self.handles.append(head.state_encoder.register_forward_hook(keep("state_features")))
        self.handles.append(head.model.timestep_encoder.register_forward_hook(keep("temb")))
        self.handles.append(head.action_encoder.register_forward_hook(keep("action_encoder")))
        for i, blk in enumerate(head.model.transformer_blocks):
            self.handles.append(blk.register_forward_hook(keep(f"dit_block.{i}")))
        self.handles.append(head.model.register_forward_hook(keep("dit_out")))
        self.handles.append(head.action_decoder.register_forward_hook(keep("decoder_out")))

    def remove(self):
        for h in self.handles:
            h.remove()


def run_head(model: TinyN16, features, image_mask, attn_mask, state, emb_id, noise, t: dict, prefix: str):
    """GR00TN17ActionHead.get_action (vlln -> state encoder -> 4 Euler steps) with torch.randn replaced during
    get_action_with_features by `noise`; records the VL embeddings after vlln, state features, per-step temb,
    action-encoder output + position embedding input, DiT output, decoder output and velocity, each DiT block's
    output at step 0, and action_pred."""
    from transformers.feature_extraction_utils import BatchFeature

    head = model.action_head
    probes = HeadProbes(head)
    log: list = []
    bo = BatchFeature(data={"backbone_features": features.clone(), "backbone_attention_mask": attn_mask.clone(),
                            "image_mask": image_mask.clone()})
    ai = BatchFeature(data={"state": state.clone(), "embodiment_id": emb_id.clone()})
    with torch.no_grad(), injected_noise(head, noise, log):
        out = head.get_action(bo, ai)
    probes.remove()
    if len(log) != 1:
        raise RuntimeError(f"noise draws {log}")
    r = probes.rec
    steps = head.num_inference_timesteps
    t[f"{prefix}.vl_embeds"] = r["vlln"][0]
    t[f"{prefix}.state_features"] = r["state_features"][0]
    for k in range(steps):
        t[f"{prefix}.temb.step{k}"] = r["temb"][k]
        t[f"{prefix}.dit_out.step{k}"] = r["dit_out"][k]
        t[f"{prefix}.decoder_out.step{k}"] = r["decoder_out"][k]
        t[f"{prefix}.velocity.step{k}"] = r["decoder_out"][k][:, -MODEL_HORIZON:].contiguous()
    t[f"{prefix}.action_encoder.step0"] = r["action_encoder"][0]
    for i in range(len(head.model.transformer_blocks)):
        t[f"{prefix}.dit_block.{i}.step0"] = r[f"dit_block.{i}"][0]
    t[f"{prefix}.action_pred"] = out["action_pred"]
    # the sampler by hand from the recorded velocities: x_{k+1} = x_k + v_k / 4
    x = noise.clone()
    for k in range(steps):
        x = x + (1.0 / steps) * t[f"{prefix}.velocity.step{k}"]
    if not torch.equal(x, out["action_pred"]):
        raise RuntimeError("Euler steps do not reproduce action_pred")
    return out["action_pred"], log


def finish(t: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    out = {}
    for k, v in t.items():
        v = v.detach()
        if v.dtype == torch.bool:
            v = v.to(torch.uint8)
        if v.is_floating_point():
            if v.dtype != torch.float32:
                raise RuntimeError(f"{k} is {v.dtype}")
            if not torch.isfinite(v).all():
                raise RuntimeError(f"{k} has non-finite values")
        out[k] = v.contiguous()
    return out


def common_meta(block: str, ran: dict, restated: dict, extra: dict) -> dict[str, str]:
    meta = {
        "block": block,
        "versions": json.dumps(versions()),
        "ran_upstream": json.dumps(ran),
        "restated_from_isaac_gr00t": json.dumps(restated),
        "weights": "checkpoint/ shards (bfloat16), upcast to float32; every computation in float32 on CPU, "
                   f"torch threads {torch.get_num_threads()}, attention 'eager'",
        "generator": GENERATOR,
    }
    meta.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in extra.items()})
    return meta


# ----------------------------------------------------------------------------------------------
# Block fixtures

VISION_IMAGES = {
    # name: (H, W, seed) -> patch grid H/14 x W/14; none equals the 4x4 table except 'table'
    "square6": (84, 84, 101),
    "wide4x6": (56, 84, 102),
    "tall8x4": (112, 56, 103),
    "table4x4": (56, 56, 104),
}


def block_vision(model, out: Path) -> dict:
    t: dict = {}
    vits = {}
    for name, (h, w, seed) in VISION_IMAGES.items():
        frame = draw_frame(h, w, seed)
        t[f"{name}.image"] = torch.from_numpy(frame)
        vits[name] = run_vision(model, eagle_pixel_values(frame), t, name)
    meta = common_meta(
        "SigLIP2 vision tower",
        {"transformers.Siglip2VisionModel": "forward(pixel_values=patches [1,N,588], pixel_attention_mask=ones "
         "[1,N], spatial_shapes=[[H/14, W/14]]), one image per call, eager attention; last_hidden_state is after "
         "post_layernorm; the pooling head runs but is unused",
         "transformers convert_image_to_patches": "patch order (py, px, c)"},
        {"pixel values": src("gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/image_processing_eagle3_vl_fast.py"),
         "one image at a time, no windows / rope": src(
             "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/modeling_siglip2.py")},
        {"images": {k: list(v[:2]) for k, v in VISION_IMAGES.items()},
         "tensors": "<img>.image uint8 HWC (draw_frame), <img>.patches [1,N,588] (pixel values (x - 127.5) / "
                    "127.5 in float32, cut into 14x14 patches flattened (py, px, c)), <img>.spatial_shapes "
                    "[1,2] int64, <img>.pos_embed [N,32] (4x4 table "
                    "resized by F.interpolate bilinear, align_corners False, antialias True, row-major), "
                    "<img>.embeddings [1,N,32] (patch_embedding + pos_embed), <img>.layer.<i> [1,N,32] encoder "
                    "layer outputs, <img>.last_hidden_state [1,N,32]"},
    )
    write(out / "blocks" / "vision", t, meta)
    return vits


def block_projector(model, vits: dict, out: Path) -> dict:
    t: dict = {}
    rows = {}
    for name, (h, w, _s) in VISION_IMAGES.items():
        t[f"{name}.input"] = vits[name]
        rows[name] = run_projector(model, vits[name], (h // PATCH, w // PATCH), t, name)
    meta = common_meta(
        "Eagle projector (pixel unshuffle x2 + mlp1)",
        {"torch.nn": "F.pixel_unshuffle and the mlp1 nn.Sequential (LayerNorm eps 1e-5, Linear, GELU exact, "
                     "Linear) with the checkpoint's backbone.model.mlp1.{0,1,3}"},
        {"pixel_shuffle_back + mlp1": src("gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/modeling_eagle3_vl.py")},
        {"tensors": "<img>.input [1,N,32] (= the vision block's last_hidden_state), <img>.unshuffled [N/4,128] "
                    "(channel c*4 + dy*2 + dx, tokens in raster order of the half-size grid), <img>.mlp1.0 "
                    "(LayerNorm), .mlp1.1 (Linear), .mlp1.2 (GELU), <img>.out [N/4,64]"},
    )
    write(out / "blocks" / "projector", t, meta)
    return rows


def prompt_text(tok, language: str, n_images: int) -> str:
    conv = [{"role": "user", "content": [{"type": "text", "text": language}]
             + [{"type": "image", "image": None} for _ in range(n_images)]}]
    return tok.apply_chat_template(conv, tokenize=False, add_generation_prompt=False)


def expand_images(text: str, tokens_per_image: list[int]) -> str:
    """Eagle3_VLProcessor.replace_media_placeholder for images: <image-k> -> '<image k>' + '<img>' +
    n_k * '<IMG_CONTEXT>' + '</img>' with n_k = H*W // (28*28)."""
    def repl(m):
        k = int(m.group(2))
        return f"<image {k}><img>{'<IMG_CONTEXT>' * tokens_per_image[k - 1]}</img>"

    return re.sub(r"<(image|video)-(\d+)>", repl, text)


def block_llm(model, tok, ids, rows: dict, out: Path) -> dict:
    """A left-padded batch of two prompts (the Gr00tN1d6DataCollator pads with padding_side 'left')."""
    samples = [
        ("pick up the red cube and place it in the bowl", ["square6"]),
        ("stack the green cube on top of the yellow one", ["wide4x6", "tall8x4"]),
    ]
    texts, all_rows = [], []
    for lang, imgs in samples:
        text = prompt_text(tok, lang, len(imgs))
        texts.append(expand_images(text, [rows[i].shape[0] for i in imgs]))
        all_rows += [rows[i] for i in imgs]
    enc = tok(texts, padding=True, return_tensors="pt")
    input_ids, mask = enc["input_ids"], enc["attention_mask"]
    if tok.padding_side != "left" or mask[:, 0].all():
        raise RuntimeError("expected left padding of different lengths")
    image_rows = torch.cat(all_rows, 0)
    embeds = splice(model, input_ids, image_rows, ids["<IMG_CONTEXT>"])
    t: dict = {"input_ids": input_ids, "attention_mask": mask, "image_rows": image_rows,
               "image_mask": (input_ids == ids["<IMG_CONTEXT>"]), "inputs_embeds": embeds}
    feats = run_llm(model, embeds, mask, t, "out")
    # each prompt alone (batch 1, no padding) agrees with its padded row on the valid tokens
    starts = 0
    for b, (lang, imgs) in enumerate(samples):
        n_img = sum(rows[i].shape[0] for i in imgs)
        valid = mask[b].bool()
        ids1 = input_ids[b:b + 1, valid]
        e1 = splice(model, ids1, image_rows[starts:starts + n_img], ids["<IMG_CONTEXT>"])
        f1 = run_llm(model, e1, torch.ones_like(ids1), None, "")
        t[f"single{b}.last_hidden_state"] = f1
        err = (f1[0] - feats[b, valid]).abs().max().item()
        if err > 1e-5:
            raise RuntimeError(f"padded vs unpadded prompt {b}: {err}")
        starts += n_img
    meta = common_meta(
        "Qwen3 LLM (select_layer layers)",
        {"transformers.Qwen3Model": f"{SELECT_LAYER} layers (config num_hidden_layers {QWEN3['num_hidden_layers']} "
                                    "cut like EagleBackbone pops them), forward(inputs_embeds, attention_mask, "
                                    "position_ids None, output_hidden_states), eager attention",
         "transformers.AutoTokenizer": "the stand-in eagle/ tokenizer, padding=True, padding_side left"},
        {"embedding splice, hidden_states[-1]": src(
            "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/modeling_eagle3_vl.py",
            "gr00t/model/modules/eagle_backbone.py"),
         "left padding": src("gr00t/model/gr00t_n1d6/processing_gr00t_n1d6.py")},
        {"prompts": texts,
         "feature": "out.last_hidden_state = hidden_states[-1] = output AFTER the final RMSNorm (transformers "
                    "4.51.3 Qwen3Model appends the normed state last; 5.5.4 the same; checked equal here)",
         "padding": "rows where attention_mask == 0 (left padding) are implementation-defined (eager here, "
                    "flash-attn varlen upstream); compare only attention_mask == 1 rows. Position ids are 0..L-1 "
                    "for every row (padding not skipped), so a padded row's valid tokens start at position = "
                    "pad count; single<b>.last_hidden_state is prompt b alone (batch 1, positions from 0); RoPE "
                    "depends on position differences only, so it equals out row b's valid tokens to float "
                    "rounding (checked <= 1e-5)",
         "tensors": "input_ids [2,L] int64, attention_mask [2,L] int64, image_mask [2,L] uint8, image_rows "
                    "[sum,64] (projector outputs: square6 | wide4x6, tall8x4), inputs_embeds [2,L,64], "
                    "out.hidden_states.<i> [2,L,64] for i = 1, 2 (output of decoder layer i - 1; "
                    "hidden_states[0] is inputs_embeds), out.last_layer_prenorm [2,L,64] "
                    "(output of the last kept layer, before the norm), out.last_hidden_state [2,L,64], "
                    "single<b>.last_hidden_state [1,L_b,64]"},
    )
    write(out / "blocks" / "llm", t, meta)
    return {"features": feats, "mask": mask, "image_mask": input_ids == ids["<IMG_CONTEXT>"]}


def block_head(model, llm: dict, out: Path) -> None:
    tags = ["libero_panda", "new_embodiment"]
    emb_id = torch.tensor([N16_EMBODIMENT_IDS[tg] for tg in tags], dtype=torch.int64)
    gen = torch.Generator().manual_seed(5000)
    state = torch.zeros(2, 1, MAX_DIM)
    widths = [11, 9]  # encoded state widths of the two embodiments
    for b, wd in enumerate(widths):
        state[b, 0, :wd] = torch.rand(wd, generator=gen) * 2 - 1
    noise = torch.randn((2, MODEL_HORIZON, MAX_DIM), generator=torch.Generator().manual_seed(5001))
    t: dict = {
        "input.backbone_features": llm["features"], "input.backbone_attention_mask": llm["mask"].bool(),
        "input.image_mask": llm["image_mask"], "input.state": state, "input.embodiment_id": emb_id,
        "input.noise": noise,
    }
    pred, log = run_head(model, llm["features"], llm["image_mask"], llm["mask"].bool(), state, emb_id, noise, t,
                         "out")
    meta = common_meta(
        "action head (vlln + 4-step flow-matching sampler)",
        {"lerobot.policies.groot.groot_n1_7.GR00TN17ActionHead": "built with vl_self_attention_cfg num_layers 0 "
         "(nn.Identity) and state_history_length 1, i.e. N1.6's head; get_action(backbone_output, action_input) "
         "-> _encode_features (vlln, state_encoder) -> get_action_with_features (no 'action' in action_input: no "
         "RTC), the same 4-step Euler loop as Isaac-GR00T's released Gr00tN1d6ActionHead",
         "torch.randn": "replaced only during get_action_with_features; returned input.noise"},
        {"sampler compared line by line": src("gr00t/model/gr00t_n1d6/gr00t_n1d6.py")},
        {"noise_calls": log,
         "embodiments": {"row0": "libero_panda (2)", "row1": "new_embodiment (10)"},
         "tensors": "input.backbone_features [2,L,64] = the llm block's out.last_hidden_state (left-padded rows "
                    "included: they are masked out of every cross-attention), input.backbone_attention_mask / "
                    "input.image_mask [2,L] uint8, input.state [2,1,16], input.embodiment_id [2], input.noise "
                    "[2,8,16]; out.vl_embeds (after vlln) [2,L,64], out.state_features [2,1,32], "
                    "out.temb.step<k> [2,32], out.action_encoder.step0 [2,8,32] (before the position embedding), "
                    "out.dit_block.<i>.step0 [2,9,32], out.dit_out.step<k> [2,9,32], out.decoder_out.step<k> "
                    "[2,9,16], out.velocity.step<k> [2,8,16] (= decoder_out[:, 1:]), out.action_pred [2,8,16] "
                    "(= noise + sum_k velocity_k / 4, normalised units)",
         "timesteps": "int((k / 4) * 1000) = 0, 250, 500, 750"},
    )
    write(out / "blocks" / "action_head", t, meta)
    # batch 1 per row gives the same result (padding invariance of the head)
    for b in range(2):
        valid = llm["mask"][b].bool()
        t1: dict = {}
        p1, _ = run_head(model, llm["features"][b:b + 1, valid], llm["image_mask"][b:b + 1, valid],
                         torch.ones(1, int(valid.sum()), dtype=torch.bool), state[b:b + 1], emb_id[b:b + 1],
                         noise[b:b + 1], t1, "x")
        err = (p1[0] - pred[b]).abs().max().item()
        if err > 1e-5:
            raise RuntimeError(f"head batch-1 row {b} differs by {err}")


# ----------------------------------------------------------------------------------------------
# End-to-end cases

CASES = {
    "cam1_libero_panda": dict(
        desc="libero_panda (row 2), 1 camera 120x160: INTER_AREA to 56x75, centre crop int(0.95*) = 53x71 at "
             "(1, 2), INTER_AREA up to 56x75; smart_resize rounds 75/28 = 2.68 to 3 -> 56x84, PIL bicubic 75 -> 84 "
             "(4x6 patches, 2x3 = 6 image tokens)",
        tag="libero_panda",
        cameras=[("image", (120, 160))],
        instruction="Put the black bowl on the plate.",
        seed=1000,
    ),
    "cam2_new_embodiment": dict(
        desc="new_embodiment (row 10), 2 cameras of different sizes: front 96x128 -> 56x75 -> 53x71 -> 56x75 -> "
             "56x84 (6 tokens); wrist 100x100 -> 56x56 -> 53x53 -> 56x56 -> smart_resize 56x56, a same-size PIL "
             "resize (copy), 4x4 patches = the table size, 4 tokens; state arm[4] degenerate (min == max -> 0), "
             "gripper beyond max (clipped), base_yaw sin/cos",
        tag="new_embodiment",
        cameras=[("front", (96, 128)), ("wrist", (100, 100))],
        instruction="Pick up the red cube and place it in the bowl.",
        seed=2000,
    ),
    "long_instruction": dict(
        desc="libero_panda, 1 wide camera 60x200 -> 56x187 -> 53x177 -> 56x187 -> smart_resize 56x196 (round(6.68) "
             "= 7), PIL bicubic 187 -> 196, 4x14 patches, 2x7 = 14 tokens; a long instruction with upper case, "
             "digits, punctuation, an underscore, an apostrophe and a non-ASCII letter (formalised: lower-cased, "
             "every char outside [\\w\\s] dropped)",
        tag="libero_panda",
        cameras=[("image", (60, 200))],
        instruction=("Pick up the RED mug (the one on the LEFT), then put it 3 cm behind the blue_plate; don't "
                     "spill the café! Afterwards close the top drawer and wait 5 seconds."),
        seed=3000,
    ),
}


def raw_state(tag: str, seed: int) -> dict[str, np.ndarray]:
    """float32 [1, D] per state group: min/max groups spread over [min - 10%, max + 10%] of the range (so some
    values clip), the cam2 gripper beyond max, angles for sin/cos groups, mean/std groups around the mean."""
    emb = EMBODIMENTS[tag]
    stats = embodiment_statistics(emb)["state"]
    gen = np.random.default_rng(seed)
    out = {}
    for key, dim in emb["state"]:
        st = {k: np.array(v) for k, v in stats[key].items()}
        if key in emb["sin_cos"]:
            v = gen.uniform(-3.0, 3.0, dim)
        elif key in emb["mean_std"]:
            v = st["mean"] + gen.normal(0, 1.5, dim) * np.maximum(st["std"], 0.1)
        else:
            span = st["max"] - st["min"]
            v = st["min"] + gen.uniform(-0.1, 1.1, dim) * span
            if key == "gripper":
                v = st["max"] + 0.25 * np.maximum(span, 0.1)
        out[key] = np.round(v, 5).astype(np.float32)[None, :]
    return out


def write_inputs(case_dir: Path, cameras, seed: int):
    d = case_dir / "inputs"
    d.mkdir(parents=True, exist_ok=True)
    images, files = {}, {}
    for i, (key, (h, w)) in enumerate(cameras):
        arr = draw_frame(h, w, seed + 10 * i)
        Image.fromarray(arr, "RGB").save(d / f"{key}.png", format="PNG")
        back = decode_png(d / f"{key}.png")
        assert np.array_equal(back, arr)
        images[key], files[key] = back, f"inputs/{key}.png"
    return images, files


def run_case(model, tok, ids, name: str, spec: dict, out: Path) -> None:
    from lerobot.policies.groot.processor_groot import _transform_n1_7_image_for_vlm_albumentations as geometry

    case_dir = out / "cases" / name
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    tag = spec["tag"]
    emb = EMBODIMENTS[tag]
    images, files = write_inputs(case_dir, spec["cameras"], spec["seed"])
    t: dict = {}
    raw = raw_state(tag, spec["seed"] + 7)
    for key, _ in emb["state"]:
        t[f"input.state.{key}"] = torch.from_numpy(raw[key])
    state_np, groups = normalize_state(tag, raw)
    for key, _ in emb["state"]:
        t[f"pre.state.{key}"] = torch.from_numpy(np.ascontiguousarray(groups[key]).astype(np.float32))
    state = torch.from_numpy(state_np).reshape(1, 1, MAX_DIM)
    t["pre.state"] = state
    emb_id = torch.tensor([N16_EMBODIMENT_IDS[tag]], dtype=torch.int64)
    t["pre.embodiment_id"] = emb_id

    pvs, tokens_per_image, geometry_log = [], [], {}
    for key, _ in spec["cameras"]:
        t[f"input.image.{key}"] = torch.from_numpy(images[key])
        e = IMAGE["shortest_image_edge"]
        g = geometry(images[key], image_crop_size=None, image_target_size=[e, e], shortest_image_edge=e,
                     crop_fraction=IMAGE["crop_fraction"], letter_box_transform=False)
        t[f"pre.eagle_image.{key}"] = torch.from_numpy(np.ascontiguousarray(g))
        f = fetch_image(np.ascontiguousarray(g))
        t[f"pre.fetched_image.{key}"] = torch.from_numpy(f)
        pv = eagle_pixel_values(f)
        t[f"pre.pixel_values.{key}"] = pv
        pvs.append(pv)
        tokens_per_image.append(f.shape[0] * f.shape[1] // PIXELS_PER_TOKEN)
        geometry_log[key] = {"input": list(images[key].shape[:2]), "albumentations_eval": list(g.shape[:2]),
                             "smart_resize": list(f.shape[:2])}

    language = formalize(spec["instruction"])
    text = prompt_text(tok, language, len(pvs))
    full = expand_images(text, tokens_per_image)
    enc = tok([full], padding=True, return_tensors="pt")
    input_ids, mask = enc["input_ids"], enc["attention_mask"]
    t["pre.input_ids"], t["pre.attention_mask"] = input_ids, mask
    image_mask = input_ids == ids["<IMG_CONTEXT>"]
    t["pre.image_mask"] = image_mask

    rows = []
    for (key, _), pv in zip(spec["cameras"], pvs, strict=True):
        vr: dict = {}
        vit = run_vision(model, pv, vr, key)
        t[f"mid.vision.{key}"] = vit
        hw = tuple(int(x) for x in vr[f"{key}.spatial_shapes"][0])
        r = run_projector(model, vit, hw, None, key)
        t[f"mid.projector.{key}"] = r
        rows.append(r)
    embeds = splice(model, input_ids, torch.cat(rows, 0), ids["<IMG_CONTEXT>"])
    t["mid.inputs_embeds"] = embeds
    feats = run_llm(model, embeds, mask, None, "")
    t["mid.backbone_features"] = feats
    noise = torch.randn((1, MODEL_HORIZON, MAX_DIM), generator=torch.Generator().manual_seed(spec["seed"] + 1))
    t["input.noise"] = noise
    pred, log = run_head(model, feats, image_mask, mask.bool(), state, emb_id, noise, t, "mid")
    t["out.action_pred"] = t.pop("mid.action_pred")
    for k in [k for k in t if k.startswith("mid.dit_block.")]:
        del t[k]
    dec = decode_actions(tag, pred.numpy())
    for key, _ in emb["action"]:
        t[f"out.action.{key}"] = torch.from_numpy(dec[key].astype(np.float32))
    t["out.actions"] = torch.cat([t[f"out.action.{key}"] for key, _ in emb["action"]], dim=-1)

    meta = common_meta(
        "end to end",
        {"lerobot _transform_n1_7_image_for_vlm_albumentations": "cv2 restatement of the albumentations eval path "
         "SmallestMaxSize(E, INTER_AREA) -> FractionalCenterCrop(f) -> SmallestMaxSize(E, INTER_AREA) (called with "
         "image_target_size [E, E], which it needs to run; with shortest_image_edge and crop_fraction set it uses "
         "neither)",
         "PIL.Image.resize": "default filter (bicubic) at the smart_resize size",
         "transformers.AutoTokenizer": "stand-in eagle/ tokenizer (Qwen2Tokenizer) and its chat template",
         "transformers.Siglip2VisionModel / Qwen3Model": "as in blocks/vision and blocks/llm",
         "lerobot GR00TN17ActionHead": "as in blocks/action_head"},
        {"geometry": src("gr00t/model/gr00t_n1d6/image_augmentations.py",
                         "gr00t/model/gr00t_n1d6/processing_gr00t_n1d6.py"),
         "smart_resize, <image k> expansion": src(
             "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/processing_eagle3_vl.py"),
         "pixel values": src("gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/image_processing_eagle3_vl_fast.py"),
         "language, prompt order (text then images)": src("gr00t/model/gr00t_n1d6/processing_gr00t_n1d6.py"),
         "state normalisation, action decoding": src("gr00t/data/state_action/state_action_processor.py",
                                                     "gr00t/model/gr00t_n1d6/processing_gr00t_n1d6.py"),
         "Eagle glue": src("gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2/modeling_eagle3_vl.py",
                           "gr00t/model/modules/eagle_backbone.py")},
        {
            "case": spec["desc"],
            "embodiment_tag": tag,
            "embodiment_id": str(N16_EMBODIMENT_IDS[tag]),
            "instruction": spec["instruction"],
            "language": language,
            "prompt_template": text,
            "prompt": full,
            "prompt_tokens_decoded": tok.decode(input_ids[0].tolist(), skip_special_tokens=False),
            "camera_keys": [k for k, _ in spec["cameras"]],
            "input_files": files,
            "geometry": geometry_log,
            "image_tokens": tokens_per_image,
            "state_groups": emb["state"],
            "state_sin_cos_keys": emb["sin_cos"],
            "state_mean_std_keys": emb["mean_std"],
            "action_groups": emb["action"],
            "valid_action_horizon": emb["horizon"],
            "noise_calls": log,
            "seed": {"inputs": spec["seed"], "state": spec["seed"] + 7, "noise": spec["seed"] + 1, "weights": SEED},
        },
    )
    write(case_dir, t, meta)


def write(d: Path, t: dict, meta: dict) -> None:
    d.mkdir(parents=True, exist_ok=True)
    t = finish(t)
    write_safetensors(d / "oracle.safetensors", t, meta)
    from safetensors import safe_open

    with safe_open(str(d / "oracle.safetensors"), "pt") as f:
        assert set(f.keys()) == set(t) and all(torch.equal(f.get_tensor(k), t[k]) for k in t)


def check_tokenizer(tok, raw_tok) -> None:
    for text in CORPUS[:10] + ["<|im_start|>user\nhi<image 1><img><IMG_CONTEXT><IMG_CONTEXT></img><|im_end|>\n"]:
        a = tok(text)["input_ids"]
        b = raw_tok.encode(text).ids
        if a != b:
            raise RuntimeError(f"AutoTokenizer vs tokenizers differ on {text!r}: {a} vs {b}")


# ----------------------------------------------------------------------------------------------
# Full-size random checkpoint (benchmarks, not committed)

CACHE = Path(os.environ.get("TETHER_CACHE", Path.home() / ".cache" / "tether"))
EAGLE_NAME = "nvidia/Eagle-Block2A-2B-v2"
FULL_SEED = 7
FULL_SHARD_BYTES = 2 * 1024**3
FULL_SIGLIP2 = dict(SIGLIP2, hidden_size=1152, intermediate_size=4304, num_hidden_layers=27, num_attention_heads=16,
                    num_patches=256)
FULL_QWEN3 = dict(QWEN3, hidden_size=2048, intermediate_size=6144, num_hidden_layers=28, num_attention_heads=16,
                  num_key_value_heads=8, head_dim=128, max_position_embeddings=40960)
FULL_SELECT_LAYER = 16
FULL_VOCAB_SIZE = 151680  # embedding rows of Eagle-Block2A-2B-v2's Qwen3 (151672 tokens)
REAL_IDS = {"<|endoftext|>": 151643, "<|im_start|>": 151644, "<|im_end|>": 151645, "<IMG_CONTEXT>": 151669,
            "<img>": 151670, "</img>": 151671}
FULL_HORIZON = 50
FULL_MAX_DIM = 128
FULL_HEAD = dict(
    HEAD,
    backbone_embedding_dim=FULL_QWEN3["hidden_size"],
    hidden_size=1024,
    input_embedding_dim=1536,
    max_state_dim=FULL_MAX_DIM,
    max_action_dim=FULL_MAX_DIM,
    action_horizon=FULL_HORIZON,
    max_seq_len=1024,
    diffusion_model_cfg=dict(HEAD["diffusion_model_cfg"], num_layers=32, num_attention_heads=32,
                             attention_head_dim=48, output_dim=1024),
)
FULL_IMAGE = {"shortest_image_edge": 256, "crop_fraction": 0.95}
FULL_EMBODIMENTS = {
    "new_embodiment": dict(
        video=["front"],
        state=[("arm", 7), ("gripper", 1)],
        sin_cos=[],
        mean_std=[],
        action=[("arm", 7), ("gripper", 1)],
        action_types=["NON_EEF", "NON_EEF"],
        language="annotation.human.task_description",
        horizon=16,
        degenerate={},
        seed=71,
    ),
}


def full_meta_model(ckpt: Path) -> TinyN16:
    """The composite network (transformers Siglip2VisionModel + Qwen3Model, lerobot GR00TN17ActionHead without VL
    self-attention) on the meta device, sized from the written config.json and <model_name>/config.json."""
    cfg = json.loads((ckpt / "config.json").read_text())
    ecfg = json.loads((ckpt / cfg["model_name"] / "config.json").read_text())
    vision = {k: ecfg["vision_config"][k] for k in SIGLIP2}
    text = {k: ecfg["text_config"][k] for k in QWEN3}
    head = {k: cfg[k] for k in HEAD}
    with torch.device("meta"), contextlib.redirect_stderr(io.StringIO()):
        return TinyN16(vision=vision, text=text, select_layer=cfg["select_layer"],
                       vocab_size=ecfg["text_config"]["vocab_size"], head=head)


def full_layout(model: torch.nn.Module) -> dict[str, tuple[int, ...]]:
    """Tensor names and shapes the checkpoint stores: the state_dict (no lm_head: Qwen3Model, embeddings tied)."""
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def full_value(model: torch.nn.Module, name: str, gen: torch.Generator) -> torch.Tensor:
    """randomize()'s rule for one tensor (gr00t_oracle.init_value; the pooling head's in_proj_bias as a bias)."""
    if name.endswith("in_proj_bias"):
        shape = tuple(model.get_parameter(name).shape)
        return torch.randn(shape, generator=gen).mul_(0.05)
    return init_value(model, name, gen)[0]


def check_full_eagle(eagle: Path) -> dict[str, int]:
    """The Eagle directory loads with AutoTokenizer, encodes as tokenizer.json does and has the real ids."""
    from tokenizers import Tokenizer
    from transformers import AutoTokenizer

    raw = Tokenizer.from_file(str(eagle / "tokenizer.json"))
    tok = AutoTokenizer.from_pretrained(str(eagle))
    check_tokenizer(tok, raw)
    for content, want in REAL_IDS.items():
        if tok.convert_tokens_to_ids(content) != want or raw.token_to_id(content) != want:
            raise RuntimeError(f"{content}: {tok.convert_tokens_to_ids(content)} / {raw.token_to_id(content)}, "
                               f"wanted {want}")
    ecfg = json.loads((eagle / "config.json").read_text())
    if ecfg["image_token_index"] != REAL_IDS["<IMG_CONTEXT>"] or ecfg["text_config"]["vocab_size"] < len(tok):
        raise RuntimeError("eagle config.json: image_token_index / vocab_size")
    return {c: tok.convert_tokens_to_ids(c) for c in REAL_IDS}


def check_full_size(out: Path) -> int:
    """The written shards against the composite network built on the meta device from the written configs: the
    same tensor names and shapes, all bfloat16, an index naming every tensor; and the Eagle tokenizer's ids."""
    from safetensors import safe_open

    want = full_layout(full_meta_model(out))
    index = json.loads((out / "model.safetensors.index.json").read_text())
    have: dict[str, tuple] = {}
    for shard in sorted(set(index["weight_map"].values())):
        with safe_open(str(out / shard), "pt") as f:
            for k in f.keys():
                sl = f.get_slice(k)
                have[k] = (tuple(sl.get_shape()), sl.get_dtype())
                if index["weight_map"][k] != shard:
                    raise RuntimeError(f"{k} is in {shard}, the index says {index['weight_map'][k]}")
    if set(want) != set(have) or set(index["weight_map"]) != set(want):
        raise RuntimeError(f"names differ: {sorted(set(want) ^ set(have))[:10]}")
    for k, shape in want.items():
        if have[k] != (shape, "BF16"):
            raise RuntimeError(f"{k}: file {have[k]}, model {shape} BF16")
    n = sum(math.prod(s) for s in want.values())
    if index["metadata"]["total_size"] != 2 * n:
        raise RuntimeError("index total_size")
    cfg = json.loads((out / "config.json").read_text())
    ids = check_full_eagle(out / cfg["model_name"])
    print(f"checked {out}: {len(have)} tensors, {n} parameters, bfloat16, match the N1.6 network built from its "
          f"config.json and {cfg['model_name']}/config.json; tokenizer ids {ids}")
    return n


def cmd_full_size(args) -> None:
    import resource
    import time

    from safetensors.torch import save_file

    out = Path(args.out or CACHE / "checkpoints" / "gr00t_n16-full-random")
    if args.check_only:
        check_full_size(out)
        return
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    started = time.time()
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / "config.json").write_text(
        json.dumps(gr00t_config_json(FULL_HEAD, FULL_SELECT_LAYER, FULL_IMAGE), indent=2) + "\n")
    (out / "processor_config.json").write_text(
        json.dumps(processor_config(FULL_EMBODIMENTS, FULL_IMAGE, FULL_MAX_DIM, FULL_HORIZON), indent=2) + "\n")
    (out / "statistics.json").write_text(
        json.dumps({tag: embodiment_statistics(e) for tag, e in FULL_EMBODIMENTS.items()}, indent=2) + "\n")
    (out / "embodiment_id.json").write_text(json.dumps(N16_EMBODIMENT_IDS, indent=2) + "\n")
    raw_tok = build_tokenizer(fill_to=REAL_IDS["<|endoftext|>"])
    ids = write_eagle_dir(out / EAGLE_NAME, raw_tok, vision=FULL_SIGLIP2, text=FULL_QWEN3, vocab_size=FULL_VOCAB_SIZE)
    if {c: ids[c] for c in REAL_IDS} != REAL_IDS:
        raise RuntimeError(f"token ids {ids}")
    print(f"wrote {out / EAGLE_NAME} ({time.time() - started:.0f} s)")

    model = full_meta_model(out)
    layout = full_layout(model)
    gen = torch.Generator().manual_seed(FULL_SEED)
    shards: list[list[str]] = [[]]
    size = 0
    for name, shape in layout.items():
        nbytes = math.prod(shape) * 2
        if shards[-1] and size + nbytes > FULL_SHARD_BYTES:
            shards.append([])
            size = 0
        shards[-1].append(name)
        size += nbytes
    weight_map: dict[str, str] = {}
    total_params = 0
    for i, group in enumerate(shards):
        fname = f"model-{i + 1:05d}-of-{len(shards):05d}.safetensors"
        tensors = {}
        for name in group:
            tensors[name] = full_value(model, name, gen).to(torch.bfloat16)
            weight_map[name] = fname
            total_params += tensors[name].numel()
        save_file(tensors, str(out / fname), metadata={"format": "pt"})
        (out / fname).chmod(0o644)
        del tensors
        print(f"wrote {fname} ({len(group)} tensors, {time.time() - started:.0f} s)")
    index = {"metadata": {"total_size": 2 * total_params}, "weight_map": dict(sorted(weight_map.items()))}
    (out / "model.safetensors.index.json").write_text(json.dumps(index, indent=2) + "\n")
    del model
    elapsed = time.time() - started
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    (out / "README.md").write_text(
        "Random-weight GR00T N1.6 checkpoint with the real sizes (Eagle-Block2A-2B-v2 backbone: SigLIP2 27 x 1152, "
        "mlp1 4608 -> 2048, Qwen3 2048 wide with 16 of its 28 layers stored, vocabulary 151680; 32-block "
        "AlternateVLDiT 32 x 48, no VL self-attention; max state / action dim 128, action horizon 50), for "
        "benchmarks only.\n"
        f"Generated by `{GENERATOR} full-size` in {elapsed:.0f} s (peak RSS {peak:.1f} GB): {total_params} "
        f"parameters in {len(shards)} bfloat16 shards, every tensor drawn from one seeded normal generator (seed "
        f"{FULL_SEED}; norm weights near 1, small biases, matrices scaled by 1/sqrt(fan_in)).\n"
        "Embodiment `new_embodiment` (projector row 10), one camera `front`, state and action groups arm (7) + "
        "gripper (1), min/max normalisation, 16 valid action steps; processor_config.json: shortest_image_edge "
        "256, crop_fraction 0.95, albumentations path, sin/cos state encoding on (no sin/cos keys).\n"
        f"`{EAGLE_NAME}/` stands in for Isaac-GR00T's vendored Eagle directory (where Tether looks first): the real "
        "Eagle3_VLConfig sizes and a byte-level BPE tokenizer padded to 151643 entries so that the special tokens "
        "have Qwen3's / Eagle's real ids (<|endoftext|> 151643, <|im_start|> 151644, <|im_end|> 151645, "
        "<IMG_CONTEXT> 151669, <img> 151670, </img> 151671).\n"
    )
    print(json.dumps({"out": str(out), "params": total_params, "tensors": len(layout), "shards": len(shards),
                      "seconds": round(elapsed, 1), "peak_rss_gb": round(peak, 2)}))
    check_full_size(out)


def main(argv: list[str] | None = None) -> None:
    torch.set_num_threads(1)
    argv = sys.argv[1:] if argv is None else list(argv)
    logging.getLogger("lerobot").setLevel(logging.ERROR)
    logging.getLogger("transformers").setLevel(logging.ERROR)
    if argv and argv[0] == "full-size":
        fs = argparse.ArgumentParser(prog="gr00t_n16_oracle.py full-size",
                                     description="random-weight N1.6 checkpoint with the real sizes (benchmarks)")
        fs.add_argument("--out", default="",
                        help="default ${TETHER_CACHE:-~/.cache/tether}/checkpoints/gr00t_n16-full-random")
        fs.add_argument("--check-only", action="store_true",
                        help="only compare an existing checkpoint with the network built from its configs")
        cmd_full_size(fs.parse_args(argv[1:]))
        return
    if argv and argv[0] == "fixtures":
        argv = argv[1:]
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO_ROOT / "tests" / "fixtures" / "gr00t_n16"))
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for sub in ("checkpoint", "eagle", "blocks", "cases"):
        if (out / sub).exists():
            shutil.rmtree(out / sub)

    raw_tok = build_tokenizer()
    ids = write_eagle_dir(out / "eagle", raw_tok)
    from transformers import AutoTokenizer

    tok = AutoTokenizer.from_pretrained(str(out / "eagle"))
    tok.padding_side = "left"  # Gr00tN1d6Processor / Gr00tN1d6DataCollator set it in code
    check_tokenizer(tok, raw_tok)

    model, info = build_checkpoint(out / "checkpoint")
    print(json.dumps({"checkpoint": info}))
    with torch.no_grad():
        vits = block_vision(model, out)
        rows = block_projector(model, vits, out)
        llm = block_llm(model, tok, ids, rows, out)
        block_head(model, llm, out)
        for name, spec in CASES.items():
            run_case(model, tok, ids, name, spec, out)
            print(f"wrote {out / 'cases' / name}")


if __name__ == "__main__":
    sys.exit(main())
