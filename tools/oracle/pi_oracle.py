"""Writes pi0 / pi0.5 checkpoints in lerobot's exact on-disk layout and runs the real upstream policies on them.

Sub-commands:
  tokenizer [--out DIR]                      the stand-in PaliGemma tokenizer as a hub cache (tests/fixtures/paligemma_hub)
  fixtures  --family pi0|pi05 [--out DIR] [--cases a,b]
                                             tiny checkpoints + oracle.safetensors per case (committed test data)
  full-size --family pi0|pi05 [--out DIR]    random-weight checkpoint with the real sizes (benchmarks, not committed)

Upstream hard-codes the architecture: `get_gemma_config` in modeling_pi0 / modeling_pi05 holds the only two Gemma
variants (gemma_2b, gemma_300m), and PaliGemmaWithExpertModel builds the PaliGemma config from
`CONFIG_MAPPING["paligemma"]()` with vocabulary 257152, SigLIP so400m, vision MLP 4304 and projector width 2048.
For the tiny fixtures this script replaces, from outside and only while it builds or loads a policy, the module
attribute `get_gemma_config` (a smaller variant table) and the two model-class names the module instantiates
(`PaliGemmaForConditionalGenerationWithPiGemma`, `PiGemmaForCausalLM`) with wrappers that shrink the HF config
upstream has just built (vocabulary, SigLIP width/depth/MLP, projector width) and then construct the unchanged
upstream classes. Everything else (image preprocessing, tokenizer step, normalisation, prefix/suffix embedding,
attention masks, KV cache, Euler loop) is upstream's own code. Each fixture's metadata (`replaced`) lists the
exact values.

The tokenizer: upstream's TokenizerProcessorStep loads "google/paligemma-3b-pt-224" by hub id. A stand-in trained
with SentencePiece (paligemma_tokenizer.py) is stored as a hub cache in tests/fixtures/paligemma_hub and
HF_HUB_CACHE points there (set below, before any Hugging Face import; override with TETHER_PALIGEMMA_HUB).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
HUB_CACHE = Path(os.environ.get("TETHER_PALIGEMMA_HUB", REPO_ROOT / "tests" / "fixtures" / "paligemma_hub"))
# huggingface_hub reads this when it is first imported
os.environ["HF_HUB_CACHE"] = str(HUB_CACHE)

import argparse  # noqa: E402
import contextlib  # noqa: E402
import copy  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402
import safetensors  # noqa: E402
import safetensors.torch  # noqa: E402
import torch  # noqa: E402
from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature  # noqa: E402
from lerobot.configs.policies import PreTrainedConfig  # noqa: E402
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402
from lerobot.policies.pi0 import modeling_pi0  # noqa: E402
from lerobot.policies.pi0.configuration_pi0 import PI0Config  # noqa: E402
from lerobot.policies.pi0.processor_pi0 import make_pi0_pre_post_processors  # noqa: E402
from lerobot.policies.pi05 import modeling_pi05  # noqa: E402
from lerobot.policies.pi05.configuration_pi05 import PI05Config  # noqa: E402
from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors  # noqa: E402
from lerobot.processor import TokenizerProcessorStep  # noqa: E402
from safetensors.torch import load_file  # noqa: E402

import paligemma_tokenizer  # noqa: E402
from smolvla_oracle import (  # noqa: E402
    decode_image,
    perturb_constant_params,
    to_model_image,
    versions,
    write_images,
    write_safetensors,
)

CACHE = Path(os.environ.get("TETHER_CACHE", Path.home() / ".cache" / "tether"))
UPSTREAM_VOCAB = 257152
GEN_FIXTURES = "tools/oracle/pi_oracle.py fixtures --family {family}"


@dataclass(frozen=True)
class Family:
    name: str
    modeling: object
    config_cls: type
    policy_cls: type
    make_processors: object
    default_norm: str


FAMILIES = {
    "pi0": Family("pi0", modeling_pi0, PI0Config, modeling_pi0.PI0Policy, make_pi0_pre_post_processors, "MEAN_STD"),
    "pi05": Family(
        "pi05", modeling_pi05, PI05Config, modeling_pi05.PI05Policy, make_pi05_pre_post_processors, "QUANTILES"
    ),
}


# ----------------------------------------------------------------------------------------------
# Tiny architecture: what replaces upstream's hard-coded sizes


@dataclass(frozen=True)
class Tiny:
    """Sizes that replace upstream's hard-coded ones. Both Gemma variants keep 8 query heads and 1 KV head (as
    gemma_2b and gemma_300m have) and share head_dim, since the expert attends to the VLM's cached K/V; SigLIP
    keeps so400m's head_dim 72 (1152 / 16) and patch 14."""

    vlm: dict = field(default_factory=dict)  # gemma_2b entry of the variant table
    expert: dict = field(default_factory=dict)  # gemma_300m entry
    vocab_size: int = 0
    vision: dict = field(default_factory=dict)

    def description(self) -> dict:
        return {
            "get_gemma_config": {
                "gemma_2b": self.vlm,
                "gemma_300m": self.expert,
                "upstream": {
                    "gemma_2b": dict(width=2048, depth=18, mlp_dim=16384, num_heads=8, num_kv_heads=1, head_dim=256),
                    "gemma_300m": dict(width=1024, depth=18, mlp_dim=4096, num_heads=8, num_kv_heads=1, head_dim=256),
                },
            },
            "vocab_size": {
                "value": self.vocab_size,
                "upstream": UPSTREAM_VOCAB,
                "where": "PaliGemma text_config.vocab_size, config.vocab_size, image_token_index and the expert "
                "GemmaConfig vocab_size (its lm_head; its embed_tokens is deleted upstream)",
            },
            "vision_config": {
                **self.vision,
                "upstream": dict(
                    hidden_size=1152, num_hidden_layers=27, num_attention_heads=16, intermediate_size=4304, patch_size=14
                ),
                "image_size": "unchanged mechanism: upstream sets it from config.image_resolution",
            },
            "projection_dim": {
                "value": self.vlm["width"],
                "upstream": 2048,
                "why": "upstream hard-codes 2048 (= gemma_2b width); it must equal the VLM width",
            },
            "how": "module attributes get_gemma_config, PaliGemmaForConditionalGenerationWithPiGemma and "
            "PiGemmaForCausalLM of the modeling module are replaced while building and loading; the two class names "
            "become wrappers that edit the HF config upstream built and construct the unchanged upstream classes",
        }


TINY_A = Tiny(
    vlm=dict(width=64, depth=2, mlp_dim=128, num_heads=8, num_kv_heads=1, head_dim=16),
    expert=dict(width=32, depth=2, mlp_dim=64, num_heads=8, num_kv_heads=1, head_dim=16),
    vocab_size=paligemma_tokenizer.VOCAB_SIZE,
    vision=dict(hidden_size=144, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64, patch_size=14),
)
TINY_B = Tiny(
    vlm=dict(width=64, depth=3, mlp_dim=96, num_heads=8, num_kv_heads=1, head_dim=16),
    expert=dict(width=48, depth=3, mlp_dim=80, num_heads=8, num_kv_heads=1, head_dim=16),
    vocab_size=paligemma_tokenizer.VOCAB_SIZE,
    vision=dict(hidden_size=144, num_hidden_layers=2, num_attention_heads=2, intermediate_size=48, patch_size=14),
)


@contextlib.contextmanager
def replaced_architecture(fam: Family, tiny: Tiny | None):
    """While active, upstream's modeling module builds the tiny architecture (no-op for tiny=None)."""
    if tiny is None:
        yield
        return
    mod = fam.modeling
    saved = {
        name: getattr(mod, name)
        for name in ("get_gemma_config", "PaliGemmaForConditionalGenerationWithPiGemma", "PiGemmaForCausalLM")
    }
    paligemma_cls = saved["PaliGemmaForConditionalGenerationWithPiGemma"]
    expert_cls = saved["PiGemmaForCausalLM"]

    def get_gemma_config(variant: str):
        table = {"gemma_2b": tiny.vlm, "gemma_300m": tiny.expert}
        if variant not in table:
            raise ValueError(f"Unknown variant: {variant}")
        return mod.GemmaConfig(**table[variant])

    def paligemma(config):
        text, vision = config.text_config, config.vision_config
        text.vocab_size = tiny.vocab_size
        config.vocab_size = tiny.vocab_size
        config.image_token_index = tiny.vocab_size
        for key, value in tiny.vision.items():
            setattr(vision, key, value)
        vision.projection_dim = text.hidden_size
        config.projection_dim = text.hidden_size
        text.num_image_tokens = (vision.image_size // vision.patch_size) ** 2
        return paligemma_cls(config=config)

    def expert(config):
        config.vocab_size = tiny.vocab_size
        return expert_cls(config=config)

    mod.get_gemma_config = get_gemma_config
    mod.PaliGemmaForConditionalGenerationWithPiGemma = paligemma
    mod.PiGemmaForCausalLM = expert
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(mod, name, value)


# ----------------------------------------------------------------------------------------------
# Config, statistics, checkpoint


def make_config(fam: Family, spec: dict):
    input_features = {
        key: PolicyFeature(type=FeatureType.VISUAL, shape=(3, h, w)) for key, (h, w), _ in spec["cameras"]
    }
    input_features["observation.state"] = PolicyFeature(type=FeatureType.STATE, shape=(spec["state_dim"],))
    output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(spec["action_dim"],))}
    mode = NormalizationMode(spec.get("norm", fam.default_norm))
    kwargs = dict(
        device="cpu",
        input_features=input_features,
        output_features=output_features,
        normalization_mapping={"VISUAL": NormalizationMode.IDENTITY, "STATE": mode, "ACTION": mode},
        chunk_size=spec["chunk_size"],
        n_action_steps=spec["chunk_size"],
        num_inference_steps=spec["num_steps"],
        image_resolution=(spec["resolution"], spec["resolution"]),
        push_to_hub=False,
    )
    for key in ("max_state_dim", "max_action_dim", "tokenizer_max_length", "empty_cameras", "dtype",
                "use_relative_actions", "relative_exclude_joints", "action_feature_names"):
        if key in spec:
            kwargs[key] = spec[key]
    return fam.config_cls(**kwargs)


def make_stats(cfg, gen: np.random.Generator, *, degenerate_dim: bool, exact_dims: int = 0) -> dict:
    """Statistics shaped like a LeRobot >= 0.4 dataset's: mean/std/min/max and the quantiles q01..q99.

    `degenerate_dim`: the last state/action dimension never moved (std == 0, min == max, q01 == q99).
    `exact_dims`: the first that many state dimensions get q01 = -3, q99 = 5 (a power-of-two range), so chosen
    states normalise to exact float32 values (bin edges of pi0.5's state discretisation)."""
    stats: dict[str, dict[str, np.ndarray]] = {}
    for key, feat in {**cfg.input_features, **cfg.output_features}.items():
        if feat.type == FeatureType.VISUAL:
            if "empty_camera" in key:
                continue
            lo = gen.uniform(0.0, 0.2, (3, 1, 1)).astype(np.float32)
            hi = gen.uniform(0.8, 1.0, (3, 1, 1)).astype(np.float32)
            stats[key] = {
                "mean": gen.uniform(0.3, 0.6, (3, 1, 1)).astype(np.float32),
                "std": gen.uniform(0.1, 0.3, (3, 1, 1)).astype(np.float32),
                "min": np.zeros((3, 1, 1), np.float32),
                "max": np.ones((3, 1, 1), np.float32),
                "q01": lo,
                "q10": (lo + 0.05).astype(np.float32),
                "q50": np.full((3, 1, 1), 0.5, np.float32),
                "q90": (hi - 0.05).astype(np.float32),
                "q99": hi,
            }
            continue
        d = feat.shape[0]
        mean = gen.uniform(-40.0, 40.0, d).astype(np.float32)
        std = gen.uniform(2.0, 30.0, d).astype(np.float32)
        q01 = (mean - 2.2 * std).astype(np.float32)
        q99 = (mean + 2.4 * std).astype(np.float32)
        if key == "observation.state" and exact_dims:
            q01[:exact_dims] = -3.0
            q99[:exact_dims] = 5.0
        s = {
            "mean": mean,
            "std": std,
            "min": (q01 - 0.5 * std).astype(np.float32),
            "max": (q99 + 0.5 * std).astype(np.float32),
            "q01": q01,
            "q10": (mean - 1.2 * std).astype(np.float32),
            "q50": (mean + 0.1 * std).astype(np.float32),
            "q90": (mean + 1.3 * std).astype(np.float32),
            "q99": q99,
        }
        if degenerate_dim:  # a joint that never moved in the dataset
            for name in s:
                s[name][-1] = mean[-1]
            s["std"][-1] = 0.0
        stats[key] = s
    return stats


def build_checkpoint(
    fam: Family, ckpt: Path, cfg, *, seed: int, tiny: Tiny | None, stats: dict | None, file_dtype
) -> None:
    """Upstream policy -> perturb constant tensors -> upstream save_pretrained for policy and both pipelines."""
    if ckpt.exists():
        shutil.rmtree(ckpt)
    ckpt.mkdir(parents=True)
    with replaced_architecture(fam, tiny):
        torch.manual_seed(seed)
        policy = fam.policy_cls(cfg)
    perturb_constant_params(policy, torch.Generator().manual_seed(seed + 1))
    if file_dtype is not None:
        policy.to(file_dtype)
    policy.save_pretrained(ckpt)
    pre, post = fam.make_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(ckpt)
    post.save_pretrained(ckpt)


EMBED_KEY = "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"
LM_HEAD_KEY = "model.paligemma_with_expert.paligemma.lm_head.weight"


def drop_embed_tokens(path: Path) -> None:
    """Rewrites an upstream-saved model.safetensors without the VLM's embed_tokens (same writer, same metadata),
    the layout of the converted hub checkpoints that only carry lm_head."""
    with safetensors.safe_open(str(path), "pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys() if k != EMBED_KEY}
    assert LM_HEAD_KEY in tensors
    safetensors.torch.save_file(tensors, str(path), metadata=meta)


def load_checkpoint(fam: Family, ckpt: Path, tiny: Tiny | None):
    """Reloads policy and pipelines with upstream's loaders, and checks every saved tensor really got loaded
    (upstream's from_pretrained falls back to random weights with only a printed warning)."""
    cfg = PreTrainedConfig.from_pretrained(str(ckpt))
    cfg.device = "cpu"
    log = io.StringIO()
    with replaced_architecture(fam, tiny), contextlib.redirect_stdout(log):
        policy = fam.policy_cls.from_pretrained(str(ckpt), config=cfg)
    if "All keys loaded successfully!" not in log.getvalue():
        raise RuntimeError(f"upstream did not load {ckpt} cleanly:\n{log.getvalue()}")
    saved = load_file(str(ckpt / "model.safetensors"))
    if EMBED_KEY not in saved:  # upstream copies lm_head into embed_tokens on load
        saved[EMBED_KEY] = saved[LM_HEAD_KEY]
    current = policy.state_dict()
    for key, value in saved.items():
        if not torch.equal(current[key], value.to(current[key].dtype)):
            raise RuntimeError(f"{key} differs after loading {ckpt}")
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(ckpt))
    if cfg.dtype == "bfloat16":
        # upstream built the model in its bf16 layout (embedding scale and RoPE frequencies computed in bf16 too);
        # the float32 reference is that model cast to float32, as bench/lerobot_reference.py runs it
        policy = policy.to(torch.float32)
    policy.eval()
    return cfg, policy, pre, post


# ----------------------------------------------------------------------------------------------
# Running upstream with probes


class Probes:
    """Instance-level wrappers around upstream methods: they record inputs/outputs and call through."""

    def __init__(self, fam: Family, policy, pre):
        self.fam = fam
        self.model = policy.model
        self.pwe = policy.model.paligemma_with_expert
        self.images_in: list[torch.Tensor] = []
        self.vision_out: list[torch.Tensor] = []
        self.img_masks = None
        self.prefix = None
        self.state = None
        self.kv = None
        self.velocities: list[torch.Tensor] = []
        self.adarms: list[torch.Tensor] = []
        self.prompts: list[str] | None = None
        self._wrap(pre)

    def _wrap(self, pre):
        pwe, model = self.pwe, self.model
        orig_embed_image = pwe.embed_image
        orig_forward = pwe.forward
        orig_embed_prefix = model.embed_prefix
        orig_embed_suffix = model.embed_suffix
        orig_sample = model.sample_actions
        orig_denoise = model.denoise_step

        def embed_image(image):
            out = orig_embed_image(image)
            self.images_in.append(image.detach().clone())
            self.vision_out.append(out.detach().clone())
            return out

        def embed_prefix(*args, **kwargs):
            out = orig_embed_prefix(*args, **kwargs)
            self.prefix = tuple(t.detach().clone() for t in out)
            return out

        def embed_suffix(*args, **kwargs):
            out = orig_embed_suffix(*args, **kwargs)
            if out[3] is not None:
                self.adarms.append(out[3].detach().clone())
            return out

        def sample_actions(images, img_masks, tokens, masks, *args, **kwargs):
            self.img_masks = torch.stack([m.detach().clone() for m in img_masks], dim=1)
            if self.fam.name == "pi0":
                self.state = args[0].detach().clone()
            return orig_sample(images, img_masks, tokens, masks, *args, **kwargs)

        def forward(*args, **kwargs):
            out = orig_forward(*args, **kwargs)
            embeds = kwargs.get("inputs_embeds")
            if self.kv is None and embeds is not None and embeds[1] is None:
                self.kv = [  # [B, kv_heads, L, head_dim] -> [B, L, kv_heads, head_dim]
                    (layer.keys.detach().transpose(1, 2).contiguous(), layer.values.detach().transpose(1, 2).contiguous())
                    for layer in out[1].layers
                ]
            return out

        def denoise_step(*args, **kwargs):
            v = orig_denoise(*args, **kwargs)
            self.velocities.append(v.detach().clone())
            return v

        pwe.embed_image = embed_image
        pwe.forward = forward
        model.embed_prefix = embed_prefix
        model.embed_suffix = embed_suffix
        model.sample_actions = sample_actions
        model.denoise_step = denoise_step

        steps = [s for s in pre.steps if isinstance(s, TokenizerProcessorStep)]
        assert len(steps) == 1
        tok_step = steps[0]
        orig_tokenize = tok_step._tokenize_text

        def tokenize(text):
            self.prompts = list(text) if isinstance(text, list) else [text]
            return orig_tokenize(text)

        tok_step._tokenize_text = tokenize
        self.tokenizer = tok_step.input_tokenizer


def make_batch(images: dict[str, np.ndarray], state: np.ndarray, instructions: list[str]) -> dict:
    batch = {key: to_model_image(arr) for key, arr in images.items()}
    batch["observation.state"] = torch.from_numpy(state)
    batch["task"] = list(instructions)
    return batch


def run_upstream(fam: Family, ckpt: Path, tiny: Tiny | None, images, state, instructions, noise):
    cfg, policy, pre, post = load_checkpoint(fam, ckpt, tiny)
    probes = Probes(fam, policy, pre)
    with torch.no_grad():
        processed = pre(make_batch(images, state, instructions))
        actions_norm = policy.predict_action_chunk(processed, noise=noise.clone())
        actions = post(actions_norm)
    return cfg, policy, processed, probes, actions_norm, actions


# ----------------------------------------------------------------------------------------------
# Fixture cases

INSTR_SHORT = "pick up the red cube"
INSTR_LONG = "Place the 2 blue blocks, then stack 3 more on top of the tray (carefully!)"
INSTR_TRUNC = (
    "First look at the table, find the 4 green cups and the 12 red plates; then put every cup on a plate, "
    "starting with the one nearest to the left edge, and finally push the tray 25 cm forward."
)
INSTR_UNDERSCORE = " open_the_drawer and\nput the sponge inside\n"  # pi0.5 strips, then rewrites "_" and "\n" to " "

CAM1 = [("observation.images.camera1", (96, 128), "png")]
CAM3 = [
    ("observation.images.camera1", (96, 128), "png"),
    ("observation.images.camera2", (58, 44), "jpg"),
    ("observation.images.camera3", (56, 56), "png"),
]

COMMON = dict(chunk_size=8, num_steps=4, resolution=56, tiny=TINY_A, weights_seed=11, file_dtype=None)

PI0_CASES = {
    "cam1_stats": dict(
        COMMON,
        desc=(
            "1 camera (96x128 PNG, landscape: centred resize to 42x56 + 7 rows of padding top and bottom), "
            "state/action 6, MEAN_STD stats with one degenerate dimension (std 0), chunk 8, 4 steps, fp32"
        ),
        seed=1000,
        cameras=CAM1,
        state_dim=6,
        action_dim=6,
        stats=True,
        degenerate=True,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam1_lm_head_only": dict(
        COMMON,
        desc=(
            "cam1_stats' checkpoint without paligemma.model.language_model.embed_tokens.weight in model.safetensors "
            "(only paligemma.lm_head.weight, as the converted hub checkpoints ship): upstream's "
            "_fix_pytorch_state_dict_keys copies lm_head into embed_tokens on load"
        ),
        seed=1000,
        cameras=CAM1,
        state_dim=6,
        action_dim=6,
        stats=True,
        degenerate=True,
        drop_embed_tokens=True,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam3_nostats_trunc": dict(
        COMMON,
        desc=(
            "3 cameras (96x128 PNG, 58x44 portrait JPEG, 56x56 PNG = model size; upstream's int(58 / (58 / 56)) "
            "is 55, so camera2 becomes 55x42 with padding 0 top, 1 bottom, 7 left, 7 right), state/action 7, "
            "no stats (identity), item 1's instruction is longer than tokenizer_max_length 48 and is truncated"
        ),
        seed=2000,
        cameras=CAM3,
        state_dim=7,
        action_dim=7,
        stats=False,
        instructions=[INSTR_SHORT, INSTR_TRUNC],
    ),
    "cam3_missing_empty": dict(
        COMMON,
        desc=(
            "config with 3 cameras + empty_cameras 1; the batch has camera1 and camera3 only: upstream embeds "
            "camera1, camera3, then camera2 and empty_camera_0 as all -1 images with image mask 0; MEAN_STD stats"
        ),
        seed=3000,
        cameras=CAM3,
        missing=["observation.images.camera2"],
        empty_cameras=1,
        state_dim=7,
        action_dim=7,
        stats=True,
        instructions=[INSTR_LONG, INSTR_SHORT],
    ),
    "cam2_bf16": dict(
        COMMON,
        desc=(
            "2 cameras (72x96 JPEG, 80x60 PNG), model.safetensors in bfloat16 while config dtype is float32 "
            "(upstream upcasts on load), state 5 / action 4, MEAN_STD stats"
        ),
        seed=4000,
        cameras=[("observation.images.top", (72, 96), "jpg"), ("observation.images.wrist", (80, 60), "png")],
        state_dim=5,
        action_dim=4,
        stats=True,
        file_dtype=torch.bfloat16,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam1_config_bf16": dict(
        COMMON,
        desc=(
            "1 camera (96x128 PNG), config dtype bfloat16 as the released checkpoints have it: upstream builds the "
            "bf16 layout (vision tower, projector, norms and projections float32, the rest bfloat16, the embedding "
            "scale and RoPE frequencies rounded to bfloat16) and the reference is that model cast to float32; "
            "state 6 / action 5, stats in the family's default normalisation"
        ),
        seed=6100,
        cameras=CAM1,
        state_dim=6,
        action_dim=5,
        stats=True,
        dtype="bfloat16",
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "variant_dims": dict(
        COMMON,
        desc=(
            "other sizes: 3 VLM + 3 expert layers (expert width 48), 2 SigLIP layers, image_resolution 112, "
            "chunk 12, 3 steps, max_state_dim 16, max_action_dim 24, tokenizer_max_length 16 (item 1 truncated), "
            "1 camera 100x150 JPEG, state 5 / action 3, MEAN_STD stats; model.safetensors in bfloat16 (to stay small; "
            "upstream computes in float32 on the upcast values)"
        ),
        seed=5000,
        weights_seed=55,
        tiny=TINY_B,
        file_dtype=torch.bfloat16,
        resolution=112,
        chunk_size=12,
        num_steps=3,
        max_state_dim=16,
        max_action_dim=24,
        tokenizer_max_length=16,
        cameras=[("observation.images.front", (100, 150), "jpg")],
        state_dim=5,
        action_dim=3,
        stats=True,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam1_relative": dict(
        COMMON,
        desc=(
            "use_relative_actions with relative_exclude_joints ['gripper'] and action_feature_names naming a "
            "'Gripper_Pos' column: both pipelines carry the relative / absolute steps, and the postprocessor adds the "
            "raw state to the unnormalised actions except column 3 (matched case-insensitively as part of the "
            "name); 1 camera (96x128 PNG), state 6 / action 5, MEAN_STD stats"
        ),
        seed=7000,
        cameras=CAM1,
        state_dim=6,
        action_dim=5,
        stats=True,
        use_relative_actions=True,
        relative_exclude_joints=["gripper"],
        action_feature_names=["shoulder_pan", "shoulder_lift", "elbow", "Gripper_Pos", "wrist_roll"],
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
}

PI05_CASES = {
    "cam1_quantiles_bins": dict(
        COMMON,
        desc=(
            "1 camera (96x128 PNG), state 8 / action 6, QUANTILES stats (q01/q99) with one degenerate dimension "
            "(q99 == q01); normalised states sit exactly on bin edges of linspace(-1, 1, 257)[:-1], just below "
            "edges, on -1 and 1 and outside [-1, 1], so np.digitize's edge behaviour is pinned; chunk 8, 4 steps"
        ),
        seed=1100,
        cameras=CAM1,
        state_dim=8,
        action_dim=6,
        stats=True,
        degenerate=True,
        bin_states=True,
        instructions=[INSTR_SHORT, INSTR_UNDERSCORE],
    ),
    "cam3_nostats_trunc": dict(
        COMMON,
        desc=(
            "3 cameras (96x128 PNG, 58x44 portrait JPEG resized to 55x42 by int() truncation, 56x56 PNG), "
            "state/action 7, no stats: the raw state is discretised as is; tokenizer_max_length 40 so item 1's "
            "prompt (long instruction + state) is truncated"
        ),
        seed=2100,
        cameras=CAM3,
        state_dim=7,
        action_dim=7,
        stats=False,
        tokenizer_max_length=40,
        raw_state_scale=0.8,
        instructions=[INSTR_SHORT, INSTR_TRUNC],
    ),
    "cam3_missing_empty": dict(
        COMMON,
        desc=(
            "config with 3 cameras + empty_cameras 1; the batch has camera1 and camera3 only: camera2 and "
            "empty_camera_0 become -1 images with image mask 0; QUANTILES stats"
        ),
        seed=3100,
        cameras=CAM3,
        missing=["observation.images.camera2"],
        empty_cameras=1,
        state_dim=7,
        action_dim=7,
        stats=True,
        instructions=[INSTR_LONG, INSTR_SHORT],
    ),
    "cam2_bf16": dict(
        COMMON,
        desc=(
            "2 cameras (72x96 JPEG, 80x60 PNG), model.safetensors in bfloat16 while config dtype is float32 "
            "(upstream upcasts on load), state 5 / action 4, QUANTILES stats"
        ),
        seed=4100,
        cameras=[("observation.images.top", (72, 96), "jpg"), ("observation.images.wrist", (80, 60), "png")],
        state_dim=5,
        action_dim=4,
        stats=True,
        file_dtype=torch.bfloat16,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam1_config_bf16": dict(
        COMMON,
        desc=(
            "1 camera (96x128 PNG), config dtype bfloat16 as the released checkpoints have it: upstream builds the "
            "bf16 layout (vision tower, projector, norms and projections float32, the rest bfloat16, the embedding "
            "scale and RoPE frequencies rounded to bfloat16) and the reference is that model cast to float32; "
            "state 6 / action 5, stats in the family's default normalisation"
        ),
        seed=6200,
        cameras=CAM1,
        state_dim=6,
        action_dim=5,
        stats=True,
        dtype="bfloat16",
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "variant_dims": dict(
        COMMON,
        desc=(
            "other sizes: 3 VLM + 3 expert layers (expert width 48), 2 SigLIP layers, image_resolution 112, "
            "chunk 12, 3 steps, max_state_dim 16, max_action_dim 24, 1 camera 100x150 JPEG, state 5 / action 3, "
            "MEAN_STD stats (normalization_mapping overridden); model.safetensors in bfloat16 (to stay small; upstream "
            "computes in float32 on the upcast values)"
        ),
        seed=5100,
        weights_seed=55,
        tiny=TINY_B,
        file_dtype=torch.bfloat16,
        resolution=112,
        chunk_size=12,
        num_steps=3,
        max_state_dim=16,
        max_action_dim=24,
        norm="MEAN_STD",
        cameras=[("observation.images.front", (100, 150), "jpg")],
        state_dim=5,
        action_dim=3,
        stats=True,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam1_relative": dict(
        COMMON,
        desc=(
            "use_relative_actions with relative_exclude_joints ['gripper', 'ROLL'] over action_feature_names: the "
            "postprocessor adds the raw state to the unnormalised actions except columns 2 ('wrist_roll') and 4 "
            "('gripper'); 1 camera (96x128 PNG), state 8 / action 6, QUANTILES stats"
        ),
        seed=7100,
        cameras=CAM1,
        state_dim=8,
        action_dim=6,
        stats=True,
        use_relative_actions=True,
        relative_exclude_joints=["gripper", "ROLL"],
        action_feature_names=["j0", "j1", "wrist_roll", "j3", "gripper", "j5"],
        instructions=[INSTR_SHORT, INSTR_UNDERSCORE],
    ),
}

CASES = {"pi0": PI0_CASES, "pi05": PI05_CASES}

BIN_EDGES = np.linspace(-1, 1, 256 + 1)[:-1]


def normalise_like_upstream(x: np.ndarray, q01: np.ndarray, q99: np.ndarray) -> np.ndarray:
    """QUANTILES in float32 torch, the formula of lerobot's normalizer (only used to choose and check states)."""
    t, lo, hi = torch.from_numpy(x), torch.from_numpy(q01), torch.from_numpy(q99)
    denom = hi - lo
    denom = torch.where(denom == 0, torch.tensor(1e-8, dtype=torch.float32), denom)
    return (2.0 * (t - lo) / denom - 1.0).numpy()


def bin_edge_states(stats: dict, state_dim: int) -> tuple[np.ndarray, list[list[int]]]:
    """States (robot units) whose normalised values land on chosen bin edges; returns them and the bins
    np.digitize must give. Dimensions 0..state_dim-2 use q01 = -3, q99 = 5 (exact); the last is degenerate."""
    st = stats["observation.state"]
    q01, q99 = st["q01"], st["q99"]
    exact = state_dim - 1
    # normalised targets: exact edges, -1, 1, outside, just below an edge (filled in below)
    targets = [
        [-1.0, BIN_EDGES[1], 0.0, BIN_EDGES[255], 1.0, "below:128", BIN_EDGES[37]],
        [-1.25, 1.5, BIN_EDGES[200], "below:1", BIN_EDGES[64], "below:255", -1.0 + 2.0**-20],
    ]
    assert all(len(t) == exact for t in targets)
    states = np.zeros((2, state_dim), np.float32)
    for b, row in enumerate(targets):
        for d, v in enumerate(row):
            if isinstance(v, str):
                k = int(v.split(":")[1])
                x = np.float32(4.0 * (BIN_EDGES[k] + 1.0) - 3.0)
                # step down one float32 ulp at a time until the normalised value drops below the edge
                while normalise_like_upstream(np.array([x]), q01[d : d + 1], q99[d : d + 1])[0] >= BIN_EDGES[k]:
                    x = np.nextafter(x, np.float32(-np.inf))
                states[b, d] = x
            else:
                states[b, d] = np.float32(4.0 * (v + 1.0) - 3.0)
        states[b, -1] = st["q01"][-1]  # the degenerate dimension sits on its single value: normalised -1
    norm = normalise_like_upstream(states, q01, q99)
    bins = (np.digitize(norm, bins=BIN_EDGES) - 1).tolist()
    for b, row in enumerate(targets):
        for d, v in enumerate(row):
            if not isinstance(v, str):
                assert norm[b, d] == np.float32(v), (b, d, norm[b, d], v)
    return states, bins


def stats_note(fam: Family, stats_present: bool, norm: str) -> str:
    if not stats_present:
        return (
            "absent: the normalizer/unnormalizer steps are saved with no state file and pass state and actions "
            f"through unchanged, although normalization_mapping says {norm}; out.actions == out.actions_normalized"
            + ("; pi0.5 discretises the raw state" if fam.name == "pi05" else "")
        )
    if norm == "MEAN_STD":
        how = "state: (x - mean) / (std + 1e-8); action out: y * std + mean (no eps)"
    else:
        how = (
            "state: 2 * (x - q01) / d - 1 and action out: (y + 1) * d / 2 + q01, with d = q99 - q01 replaced "
            "by 1e-8 where it is 0"
        )
    return f"present ({norm}); {how}; images are IDENTITY (their stats are stored but unused)"


def make_state(spec: dict, stats: dict, gen: np.random.Generator) -> tuple[np.ndarray, list | None]:
    B, sd = 2, spec["state_dim"]
    st = stats["observation.state"]
    if spec.get("bin_states"):
        return bin_edge_states(stats, sd)
    if spec.get("raw_state_scale"):  # no stats: a state already in about [-1, 1]
        return (gen.uniform(-1.0, 1.0, (B, sd)) * spec["raw_state_scale"]).astype(np.float32), None
    state = (st["mean"][None, :] + gen.normal(0, 1, (B, sd)).astype(np.float32) * np.maximum(st["std"], 1.0)[None, :])
    state = state.astype(np.float32)
    if spec.get("degenerate"):
        state[:, -1] = st["mean"][-1]
    return state, None


def run_case(fam: Family, name: str, spec: dict, out_root: Path) -> Path:
    case_dir = out_root / name
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    B = 2
    cfg = make_config(fam, spec)
    gen = np.random.default_rng(spec["seed"])
    norm = spec.get("norm", fam.default_norm)
    stats = make_stats(
        cfg,
        np.random.default_rng(spec["weights_seed"] + 7),
        degenerate_dim=spec.get("degenerate", False),
        exact_dims=spec["state_dim"] - 1 if spec.get("bin_states") else 0,
    )
    ckpt = case_dir / "checkpoint"
    build_checkpoint(
        fam, ckpt, cfg, seed=spec["weights_seed"], tiny=spec["tiny"], stats=stats if spec["stats"] else None,
        file_dtype=spec["file_dtype"],
    )
    if spec.get("drop_embed_tokens"):
        drop_embed_tokens(ckpt / "model.safetensors")
    missing = spec.get("missing", [])
    present = [c for c in spec["cameras"] if c[0] not in missing]
    images, files = write_images(case_dir, present, B, spec["seed"])
    state, expected_bins = make_state(spec, stats, gen)
    noise = torch.from_numpy(gen.standard_normal((B, cfg.chunk_size, cfg.max_action_dim)).astype(np.float32))
    record_oracle(
        fam, case_dir, ckpt, spec["tiny"], images, files, state, noise, spec, norm=norm,
        generator=GEN_FIXTURES.format(family=fam.name), expected_bins=expected_bins,
    )
    return case_dir


def parse_state_bins(prompts: list[str]) -> list[list[int]]:
    out = []
    for p in prompts:
        part = p.split("State: ", 1)[1].split(";", 1)[0]
        out.append([int(v) for v in part.split(" ")])
    return out


def record_oracle(
    fam: Family, case_dir: Path, ckpt: Path, tiny: Tiny | None, images: dict, files: dict, state: np.ndarray,
    noise: torch.Tensor, spec: dict, *, norm: str, generator: str, expected_bins=None, extra_meta: dict | None = None,
) -> None:
    """Runs upstream on `ckpt` and writes `case_dir/oracle.safetensors`: inputs, intermediates, outputs."""
    cfg, policy, processed, probes, actions_norm, actions = run_upstream(
        fam, ckpt, tiny, images, state, spec["instructions"], noise
    )
    image_keys = list(cfg.image_features)
    present = [k for k in image_keys if k in images]
    model_order = present + [k for k in image_keys if k not in images]
    assert len(probes.images_in) == len(model_order) and probes.kv is not None and probes.prefix is not None
    n_layers = len(policy.model.paligemma_with_expert.paligemma.model.language_model.layers)

    t: dict[str, torch.Tensor] = {"input.state": torch.from_numpy(state), "input.noise": noise}
    for key in present:
        t[f"input.image.{key}"] = torch.from_numpy(images[key])
    for key, img, vis in zip(model_order, probes.images_in, probes.vision_out, strict=True):
        t[f"pre.pixels.{key}"] = img.float()
        t[f"mid.vision.{key}"] = vis.float()
    t["pre.image_masks"] = probes.img_masks.to(torch.uint8)
    t["pre.lang_tokens"] = processed["observation.language.tokens"].to(torch.int64)
    t["pre.lang_mask"] = processed["observation.language.attention_mask"].to(torch.uint8)
    if fam.name == "pi0":
        t["pre.state"] = probes.state.float()
    else:
        t["pre.state"] = processed["observation.state"].float()
        bins = parse_state_bins(probes.prompts)
        if expected_bins is not None:
            assert bins == expected_bins, (bins, expected_bins)
        t["pre.state_bins"] = torch.tensor(bins, dtype=torch.int64)
        t["mid.adarms_cond.step0"] = probes.adarms[0].float()
    embs, pad_masks, _att = probes.prefix
    t["mid.prefix_embs"] = embs.float()
    t["mid.prefix_pad_mask"] = pad_masks.to(torch.uint8)
    for layer in (0, n_layers - 1):
        k, v = probes.kv[layer]
        t[f"mid.prefix_k.{layer}"] = k.float()
        t[f"mid.prefix_v.{layer}"] = v.float()
    t["mid.velocity.step0"] = probes.velocities[0].float()
    t["out.actions_normalized"] = actions_norm.float()
    t["out.actions"] = actions.float()
    t = {k: v.contiguous() for k, v in t.items()}

    tok = probes.tokenizer
    file_dtypes = sorted({str(v.dtype) for v in load_file(str(ckpt / "model.safetensors")).values()})
    vlm_cfg = policy.model.paligemma_with_expert.paligemma.config
    expert_cfg = policy.model.paligemma_with_expert.gemma_expert.config
    meta = {
        "versions": json.dumps(versions()),
        "family": fam.name,
        "instructions": json.dumps(spec["instructions"]),
        "prompts": json.dumps(probes.prompts),
        "cameras": json.dumps(model_order),
        "missing_cameras": json.dumps([k for k in image_keys if k not in images]),
        "input_files": json.dumps(files),
        "case": spec["desc"],
        "stats": stats_note(fam, spec["stats"], norm),
        "seed": json.dumps({"inputs": spec["seed"], "weights": spec["weights_seed"]}),
        "checkpoint_file_dtypes": ",".join(file_dtypes),
        "checkpoint_param_dtype_after_load": ",".join(sorted({str(p.dtype) for p in policy.parameters()})),
        "tokenizer": json.dumps(
            {
                "repo_id": paligemma_tokenizer.REPO_ID,
                "hub_cache": "tests/fixtures/paligemma_hub",
                "class": type(tok).__name__,
                "vocab_size": len(tok),
                "bos_token_id": tok.bos_token_id,
                "pad_token_id": tok.pad_token_id,
                "padding": "max_length",
                "padding_side": "right",
                "truncation_side": tok.truncation_side,
                "max_length": cfg.tokenizer_max_length,
                "prompt": "task + '\\n' when missing (pi0_new_line_processor)"
                if fam.name == "pi0"
                else "'Task: ' + task.strip() with '_' and '\\n' -> ' ' + ', State: ' + bins + ';\\nAction: '",
            }
        ),
        "config": json.dumps(
            {
                "chunk_size": cfg.chunk_size,
                "num_inference_steps": cfg.num_inference_steps,
                "max_state_dim": cfg.max_state_dim,
                "max_action_dim": cfg.max_action_dim,
                "image_resolution": list(cfg.image_resolution),
                "tokenizer_max_length": cfg.tokenizer_max_length,
                "empty_cameras": cfg.empty_cameras,
                "dtype": cfg.dtype,
                "normalization_mapping": {k: v.value for k, v in cfg.normalization_mapping.items()},
                "vlm": {
                    "hidden_size": vlm_cfg.text_config.hidden_size,
                    "num_hidden_layers": vlm_cfg.text_config.num_hidden_layers,
                    "intermediate_size": vlm_cfg.text_config.intermediate_size,
                    "num_attention_heads": vlm_cfg.text_config.num_attention_heads,
                    "num_key_value_heads": vlm_cfg.text_config.num_key_value_heads,
                    "head_dim": vlm_cfg.text_config.head_dim,
                    "rms_norm_eps": vlm_cfg.text_config.rms_norm_eps,
                    "rope_theta": vlm_cfg.text_config.rope_parameters["rope_theta"]
                    if getattr(vlm_cfg.text_config, "rope_parameters", None)
                    else getattr(vlm_cfg.text_config, "rope_theta", None),
                    "vocab_size": vlm_cfg.text_config.vocab_size,
                },
                "expert": {
                    "hidden_size": expert_cfg.hidden_size,
                    "num_hidden_layers": expert_cfg.num_hidden_layers,
                    "intermediate_size": expert_cfg.intermediate_size,
                    "num_attention_heads": expert_cfg.num_attention_heads,
                    "num_key_value_heads": expert_cfg.num_key_value_heads,
                    "head_dim": expert_cfg.head_dim,
                    "use_adarms": bool(getattr(expert_cfg, "use_adarms", False)),
                },
                "vision": {
                    "hidden_size": vlm_cfg.vision_config.hidden_size,
                    "num_hidden_layers": vlm_cfg.vision_config.num_hidden_layers,
                    "num_attention_heads": vlm_cfg.vision_config.num_attention_heads,
                    "intermediate_size": vlm_cfg.vision_config.intermediate_size,
                    "patch_size": vlm_cfg.vision_config.patch_size,
                    "image_size": vlm_cfg.vision_config.image_size,
                    "layer_norm_eps": vlm_cfg.vision_config.layer_norm_eps,
                    "hidden_act": vlm_cfg.vision_config.hidden_act,
                },
            }
        ),
        "replaced": json.dumps(tiny.description() if tiny is not None else None),
        "generator": generator,
        **(extra_meta or {}),
    }
    write_safetensors(case_dir / "oracle.safetensors", t, meta)
    check = safetensors.safe_open(str(case_dir / "oracle.safetensors"), "pt")
    assert set(check.keys()) == set(t) and all(torch.equal(check.get_tensor(k), t[k]) for k in t)


# ----------------------------------------------------------------------------------------------
# Commands


def cmd_tokenizer(args) -> None:
    snapshot = paligemma_tokenizer.write_hub_cache(Path(args.out))
    print(f"wrote {snapshot}")


def ensure_tokenizer() -> None:
    repo = HUB_CACHE / ("models--" + paligemma_tokenizer.REPO_ID.replace("/", "--"))
    if not (repo / "refs" / "main").exists():
        paligemma_tokenizer.write_hub_cache(HUB_CACHE)


def cmd_fixtures(args) -> None:
    fam = FAMILIES[args.family]
    out = Path(args.out or REPO_ROOT / "tests" / "fixtures" / fam.name)
    out.mkdir(parents=True, exist_ok=True)
    ensure_tokenizer()
    cases = CASES[fam.name]
    names = args.cases.split(",") if args.cases else list(cases)
    for name in names:
        if name not in cases:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(cases)}")
        d = run_case(fam, name, cases[name], out)
        print(f"wrote {d}")


def count_params(fam: Family) -> dict:
    """Parameters of the real-size policy, counted on the meta device (nothing allocated)."""
    cfg = make_config(fam, FULL_SPEC)
    cfg.device = "meta"
    with torch.device("meta"):
        policy = fam.policy_cls(cfg)
    return param_breakdown(policy)


def param_breakdown(policy) -> dict:
    """Parameter counts: total, per part, and the two lm_heads (saved, never used for actions)."""
    parts: dict[str, int] = {}
    for name, p in policy.named_parameters():
        key = name.removeprefix("model.").removeprefix("paligemma_with_expert.")
        for prefix in (
            "paligemma.model.vision_tower",
            "paligemma.model.multi_modal_projector",
            "paligemma.model.language_model.embed_tokens",
            "paligemma.model.language_model",
            "paligemma.lm_head",
            "gemma_expert.lm_head",
            "gemma_expert.model",
        ):
            if key.startswith(prefix):
                key = prefix
                break
        else:
            key = "projections"
        parts[key] = parts.get(key, 0) + p.numel()
    total = sum(parts.values())
    heads = parts.get("paligemma.lm_head", 0) + parts.get("gemma_expert.lm_head", 0)
    return {"total": total, "without_lm_heads": total - heads, "parts": parts}


FULL_SPEC = dict(
    cameras=[("observation.images.base_0_rgb", (224, 224), "png")],
    state_dim=8,
    action_dim=7,
    chunk_size=50,
    num_steps=10,
    resolution=224,
    dtype="bfloat16",
)


def upstream_layout(fam: Family, cfg) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """Names, shapes and dtypes of the policy upstream builds for `cfg` (on the meta device: nothing allocated)."""
    cfg = copy.deepcopy(cfg)
    cfg.device = "meta"
    with torch.device("meta"), contextlib.redirect_stdout(io.StringIO()):
        policy = fam.policy_cls(cfg)
    return {k: (tuple(v.shape), v.dtype) for k, v in policy.state_dict().items()}


def check_full_size(fam: Family, out: Path) -> None:
    """The written file against the policy upstream builds from the written config.json: the same tensor names,
    shapes and dtypes (what from_pretrained(strict=True) loads without casting)."""
    want = upstream_layout(fam, PreTrainedConfig.from_pretrained(str(out)))
    with safetensors.safe_open(str(out / "model.safetensors"), "pt") as f:
        have = {k: (tuple(f.get_slice(k).get_shape()), f.get_slice(k).get_dtype()) for k in f.keys()}
    names = {torch.bfloat16: "BF16", torch.float32: "F32"}
    assert set(want) == set(have), (sorted(set(want) ^ set(have)))[:10]
    for k, (shape, dtype) in want.items():
        assert have[k] == (shape, names[dtype]), (k, have[k], shape, dtype)
    print(f"checked {out / 'model.safetensors'}: {len(have)} tensors match upstream's {fam.name} policy")


def cmd_full_size(args) -> None:
    fam = FAMILIES[args.family]
    out = Path(args.out or CACHE / "checkpoints" / f"{fam.name}-full-random")
    if args.check_only:
        check_full_size(fam, out)
        return
    started = time.time()
    cfg = make_config(fam, FULL_SPEC)
    cfg.device = "cpu"
    stats = make_stats(cfg, np.random.default_rng(5), degenerate_dim=False)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    # Upstream builds in float32 and then casts (to_bfloat16_for_selected_params): 16 GB for pi0 at the peak.
    # Building under a bfloat16 default dtype keeps the peak near the bf16 size; upstream itself casts the
    # vision tower, the projector and the norms back to float32.
    torch.manual_seed(5)
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.bfloat16)
    try:
        policy = fam.policy_cls(cfg)
    finally:
        torch.set_default_dtype(old)
    # the bfloat16 default also made the float32 parts of upstream's bf16 layout bfloat16 (PI0Pytorch's own
    # projections action_in/out_proj, state_proj, time MLPs stay float32 upstream): cast every tensor to the
    # dtype upstream gives it for this config
    layout = upstream_layout(fam, cfg)
    with torch.no_grad():
        for name, p in policy.named_parameters():
            if p.dtype != layout[name][1]:
                p.data = p.data.to(layout[name][1])
    # norms at zero (weight 1) and the zero-init adaRMS dense weights would make parts of the network trivial
    perturb_constant_params(policy, torch.Generator().manual_seed(6))
    breakdown = param_breakdown(policy)
    n_params = breakdown["total"]
    policy.save_pretrained(out)
    pre, post = fam.make_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    dtypes: dict[str, int] = {}
    for p in policy.parameters():
        dtypes[str(p.dtype)] = dtypes.get(str(p.dtype), 0) + p.numel()
    elapsed = time.time() - started
    norm = fam.default_norm
    (out / "README.md").write_text(
        f"Random-weight {fam.name} checkpoint with the real sizes (PaliGemma gemma_2b + SigLIP so400m, "
        "gemma_300m action expert), for benchmarks only.\n"
        f"Generated by `tools/oracle/run.sh pi_oracle.py full-size --family {fam.name}` in {elapsed:.0f} s.\n"
        f"{n_params} parameters ({breakdown['without_lm_heads']} without the two lm_heads: "
        f"{json.dumps(breakdown['parts'])}); config dtype bfloat16: the dtypes upstream gives each tensor for "
        "it, i.e. the vision tower, the projector, the RMS norms and the action/state/time projections float32, the "
        "Gemma layers, embeddings and lm_heads bfloat16 (parameters per dtype: "
        f"{json.dumps(dtypes)}). Constant tensors (norm weights, zero-init adaRMS dense weights) were perturbed.\n"
        f"One camera 224x224, state 8, action 7, chunk 50, 10 steps, {norm} stats. The tokenizer is the stand-in "
        "in tests/fixtures/paligemma_hub (run with HF_HUB_CACHE pointing there); the model's vocabulary is the real "
        "257152.\n"
    )
    print(json.dumps({"out": str(out), "params": n_params, "dtypes": dtypes, "seconds": round(elapsed, 1)}))
    del policy
    check_full_size(fam, out)


def main(argv: list[str] | None = None) -> None:
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("tokenizer")
    t.add_argument("--out", default=str(HUB_CACHE))
    f = sub.add_parser("fixtures")
    f.add_argument("--family", choices=sorted(FAMILIES), required=True)
    f.add_argument("--out", default="")
    f.add_argument("--cases", default="")
    fs = sub.add_parser("full-size")
    fs.add_argument("--family", choices=sorted(FAMILIES), required=True)
    fs.add_argument("--out", default="")
    fs.add_argument("--check-only", action="store_true", help="only compare an existing checkpoint with upstream")
    c = sub.add_parser("count")
    c.add_argument("--family", choices=sorted(FAMILIES), required=True)
    args = p.parse_args(argv)
    if args.cmd == "count":
        print(json.dumps(count_params(FAMILIES[args.family])))
        return
    {"tokenizer": cmd_tokenizer, "fixtures": cmd_fixtures, "full-size": cmd_full_size}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
