"""Writes SmolVLA checkpoints in lerobot's exact on-disk layout and runs the real upstream policy on them.

Sub-commands:
  fixtures  [--out DIR] [--cases a,b]  tiny checkpoints + oracle.safetensors per case (committed test data)
  full-size [--out DIR]                random-weight checkpoint with SmolVLM2-500M / smolvla_base shapes
  demo      [--out DIR]                small random-weight demo policy plus a sample camera image

Everything runs offline: the VLM backbone config, tokenizer and processor files are generated here and
stored in the checkpoint's `vlm/` folder, which the policy config names by the relative path "vlm"
(upstream resolves it against the working directory, so inference runs with CWD = checkpoint dir).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

REPO_ROOT = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("TETHER_CACHE", Path.home() / ".cache" / "tether"))

import lerobot  # noqa: E402
import safetensors  # noqa: E402
import tokenizers  # noqa: E402
import transformers  # noqa: E402
from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature  # noqa: E402
from lerobot.configs.policies import PreTrainedConfig  # noqa: E402
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402
from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig  # noqa: E402
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy  # noqa: E402
from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors  # noqa: E402
from tokenizers import AddedToken, Tokenizer, decoders, models, pre_tokenizers, processors, trainers  # noqa: E402
from transformers import (  # noqa: E402
    AutoTokenizer,
    PreTrainedTokenizerFast,
    SmolVLMConfig,
    SmolVLMImageProcessor,
    SmolVLMProcessor,
    SmolVLMVideoProcessor,
)

# ----------------------------------------------------------------------------------------------
# Tokenizer: byte-level BPE shaped like SmolLM2's (Digits(individual) + ByteLevel pre-tokenizer,
# ByteLevel decoder), with the 128 tokens SmolVLM2 appends after the base vocabulary.

BASE_SPECIALS = ["<|endoftext|>", "<|im_start|>", "<|im_end|>"]


def smolvlm_added_tokens() -> list[str]:
    """SmolVLM2's added tokens in id order: they follow the base vocabulary directly."""
    toks = ["<global-img>"]
    toks += [f"<row_{r}_col_{c}>" for r in range(1, 7) for c in range(1, 7)]
    toks += ["<fake_token_around_image>", "<image>"]
    toks += [f"<|reserved_special_token_{i}|>" for i in range(88)]
    toks += ["<end_of_utterance>"]
    assert len(toks) == 128
    return toks


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
]


def train_tokenizer(base_vocab: int, fill_to: int | None = None) -> Tokenizer:
    """Trains the byte-level BPE on CORPUS; `fill_to` pads the base vocabulary with never-produced
    entries so the added tokens land at SmolVLM2's real ids (for the full-size checkpoint)."""
    tok = Tokenizer(models.BPE(unk_token=None, fuse_unk=False, byte_fallback=False))
    tok.normalizer = None
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Digits(individual_digits=True),
            pre_tokenizers.ByteLevel(add_prefix_space=False, trim_offsets=True, use_regex=True),
        ]
    )
    tok.post_processor = processors.ByteLevel(add_prefix_space=True, trim_offsets=False, use_regex=True)
    tok.decoder = decoders.ByteLevel(add_prefix_space=True, trim_offsets=True, use_regex=True)
    trainer = trainers.BpeTrainer(
        vocab_size=base_vocab,
        min_frequency=1,
        show_progress=False,
        special_tokens=[AddedToken(t, special=True, normalized=False) for t in BASE_SPECIALS],
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
    )
    tok.train_from_iterator(CORPUS * 4, trainer=trainer)
    if fill_to is not None:
        data = json.loads(tok.to_str())
        vocab = data["model"]["vocab"]
        while len(vocab) < fill_to:
            vocab[f"<unused_{len(vocab)}>"] = len(vocab)
        tok = Tokenizer.from_str(json.dumps(data))
    tok.add_special_tokens([AddedToken(t, special=True, normalized=False) for t in smolvlm_added_tokens()])
    return tok


def write_vlm_dir(vlm_dir: Path, *, text: dict, vision: dict, scale_factor: int, tok: Tokenizer) -> None:
    """Writes config.json, tokenizer and processor files the upstream Auto* loaders read."""
    vlm_dir.mkdir(parents=True, exist_ok=True)
    specials = {
        "fake_image_token": "<fake_token_around_image>",
        "image_token": "<image>",
        "global_image_token": "<global-img>",
        "end_of_utterance_token": "<end_of_utterance>",
    }
    hf_tok = PreTrainedTokenizerFast(
        tokenizer_object=tok,
        bos_token="<|im_start|>",
        eos_token="<end_of_utterance>",
        pad_token="<|im_end|>",
        unk_token="<|endoftext|>",
        model_max_length=8192,
        truncation_side="left",
        clean_up_tokenization_spaces=False,
        extra_special_tokens=specials,
    )
    vocab_size = tok.get_vocab_size(with_added_tokens=True)
    image_size, patch = vision["image_size"], vision["patch_size"]
    image_seq_len = (image_size // patch) ** 2 // (scale_factor**2)
    img_proc = SmolVLMImageProcessor(
        do_image_splitting=False,
        max_image_size={"longest_edge": image_size},
        size={"longest_edge": image_size},
    )
    processor = SmolVLMProcessor(
        image_processor=img_proc,
        tokenizer=hf_tok,
        video_processor=SmolVLMVideoProcessor(),
        image_seq_len=image_seq_len,
    )
    processor.save_pretrained(str(vlm_dir))
    # SmolVLM2 ships its tokenizer as GPT2Tokenizer; keep that so transformers takes the same path
    cfg_path = vlm_dir / "tokenizer_config.json"
    tok_cfg = json.loads(cfg_path.read_text())
    tok_cfg["tokenizer_class"] = "GPT2Tokenizer"
    tok_cfg["add_prefix_space"] = False
    cfg_path.write_text(json.dumps(tok_cfg, indent=2, sort_keys=True) + "\n")

    config = SmolVLMConfig(
        text_config={
            "model_type": "llama",
            "vocab_size": vocab_size,
            "max_position_embeddings": 8192,
            "rope_theta": 100000.0,
            "tie_word_embeddings": False,
            "pad_token_id": tok.token_to_id("<|im_end|>"),
            **text,
        },
        vision_config={"model_type": "smolvlm_vision", **vision},
        scale_factor=scale_factor,
        image_token_id=tok.token_to_id("<image>"),
        vocab_size=vocab_size,
        tie_word_embeddings=False,
    )
    config.save_pretrained(str(vlm_dir))


# ----------------------------------------------------------------------------------------------
# Policy construction and saving (upstream save functions only)


@contextlib.contextmanager
def working_dir(path: Path):
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


def perturb_constant_params(policy: torch.nn.Module, gen: torch.Generator) -> None:
    """Default init leaves norms at 1 and biases at 0; give every such tensor random values so a port
    that skipped a norm weight or a bias would fail its parity test."""
    with torch.no_grad():
        for name, p in policy.named_parameters():
            if not p.dtype.is_floating_point or p.numel() == 0:
                continue
            flat = p.detach().reshape(-1)
            if bool((flat == flat[0]).all()):
                scale = 0.1 if name.endswith("weight") else 0.05
                p.add_(torch.randn(p.shape, generator=gen, dtype=p.dtype) * scale)


def make_config(
    *,
    cameras: list[tuple[str, tuple[int, int]]],
    state_dim: int,
    action_dim: int,
    norm: str,
    chunk_size: int,
    num_steps: int,
    num_vlm_layers: int,
    num_expert_layers: int,
    self_attn_every_n_layers: int,
    resize: tuple[int, int],
    tokenizer_max_length: int = 48,
    expert_width_multiplier: float = 0.75,
) -> SmolVLAConfig:
    input_features = {
        key: PolicyFeature(type=FeatureType.VISUAL, shape=(3, h, w)) for key, (h, w) in cameras
    }
    input_features["observation.state"] = PolicyFeature(type=FeatureType.STATE, shape=(state_dim,))
    output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))}
    mode = NormalizationMode(norm)
    return SmolVLAConfig(
        device="cpu",
        input_features=input_features,
        output_features=output_features,
        normalization_mapping={"VISUAL": NormalizationMode.IDENTITY, "STATE": mode, "ACTION": mode},
        chunk_size=chunk_size,
        n_action_steps=chunk_size,
        num_steps=num_steps,
        vlm_model_name="vlm",
        load_vlm_weights=False,
        num_vlm_layers=num_vlm_layers,
        num_expert_layers=num_expert_layers,
        self_attn_every_n_layers=self_attn_every_n_layers,
        expert_width_multiplier=expert_width_multiplier,
        resize_imgs_with_padding=resize,
        tokenizer_max_length=tokenizer_max_length,
        push_to_hub=False,
    )


def make_stats(cfg: SmolVLAConfig, gen: np.random.Generator, *, degenerate_dim: bool) -> dict:
    """Dataset statistics shaped like a LeRobot dataset's (mean/std/min/max per feature, images (3,1,1))."""
    stats: dict[str, dict[str, np.ndarray]] = {}
    for key, feat in {**cfg.input_features, **cfg.output_features}.items():
        if feat.type == FeatureType.VISUAL:
            stats[key] = {
                "mean": gen.uniform(0.3, 0.6, (3, 1, 1)).astype(np.float32),
                "std": gen.uniform(0.1, 0.3, (3, 1, 1)).astype(np.float32),
                "min": np.zeros((3, 1, 1), np.float32),
                "max": np.ones((3, 1, 1), np.float32),
            }
            continue
        d = feat.shape[0]
        mean = gen.uniform(-40.0, 40.0, d).astype(np.float32)
        std = gen.uniform(2.0, 30.0, d).astype(np.float32)
        lo = (mean - 2.5 * std).astype(np.float32)
        hi = (mean + 2.5 * std).astype(np.float32)
        if degenerate_dim:  # a joint that never moved in the dataset: max == min, std == 0
            lo[-1] = hi[-1] = mean[-1]
            std[-1] = 0.0
        stats[key] = {"mean": mean, "std": std, "min": lo, "max": hi}
    return stats


def build_checkpoint(
    ckpt: Path,
    cfg: SmolVLAConfig,
    *,
    seed: int,
    text: dict,
    vision: dict,
    scale_factor: int,
    tok: Tokenizer,
    stats: dict | None,
    dtype: torch.dtype,
) -> None:
    if ckpt.exists():
        shutil.rmtree(ckpt)
    ckpt.mkdir(parents=True)
    write_vlm_dir(ckpt / "vlm", text=text, vision=vision, scale_factor=scale_factor, tok=tok)
    with working_dir(ckpt):
        torch.manual_seed(seed)
        policy = SmolVLAPolicy(cfg)
        perturb_constant_params(policy, torch.Generator().manual_seed(seed + 1))
        policy.to(dtype)
        policy.save_pretrained(ckpt)
        pre, post = make_smolvla_pre_post_processors(cfg, dataset_stats=stats)
        pre.save_pretrained(ckpt)
        post.save_pretrained(ckpt)


def load_checkpoint(ckpt: Path):
    """Reloads the policy and both processor pipelines with upstream's own loaders."""
    with working_dir(ckpt):
        cfg = PreTrainedConfig.from_pretrained(str(ckpt))
        cfg.device = "cpu"
        with contextlib.redirect_stdout(io.StringIO()):
            policy = SmolVLAPolicy.from_pretrained(str(ckpt), config=cfg)
        pre, post = make_pre_post_processors(cfg, pretrained_path=str(ckpt))
    policy.eval()
    return cfg, policy, pre, post


# ----------------------------------------------------------------------------------------------
# Synthetic camera images


def draw_scene(h: int, w: int, seed: int) -> Image.Image:
    """A small table-top scene: gradient background, a few coloured blocks and a disc."""
    gen = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    base = gen.uniform(40, 200, 3)
    slope = gen.uniform(-0.8, 0.8, (2, 3))
    arr = base[None, None, :] + yy[..., None] * slope[0] * (96.0 / h) + xx[..., None] * slope[1] * (96.0 / w)
    img = Image.fromarray(np.clip(arr, 0, 255).astype(np.uint8), "RGB")
    draw = ImageDraw.Draw(img)
    for _ in range(4):
        x0, y0 = int(gen.integers(0, w - 8)), int(gen.integers(0, h - 8))
        x1, y1 = x0 + int(gen.integers(6, max(7, w // 3))), y0 + int(gen.integers(6, max(7, h // 3)))
        draw.rectangle([x0, y0, x1, y1], fill=tuple(int(c) for c in gen.integers(0, 256, 3)))
    cx, cy, r = int(gen.integers(8, w - 8)), int(gen.integers(8, h - 8)), int(gen.integers(4, 12))
    draw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=tuple(int(c) for c in gen.integers(0, 256, 3)))
    draw.line([0, h - 1, w - 1, int(gen.integers(0, h))], fill=(250, 250, 250), width=2)
    return img


def draw_demo_scene(h: int = 480, w: int = 640) -> Image.Image:
    """A front-camera view for the demo: wall, wooden table, a red cube, a blue bowl and a gripper."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    wall = np.stack([200 - yy * 0.08, 205 - yy * 0.08, 212 - yy * 0.06], -1)
    horizon = int(h * 0.38)
    grain = 8.0 * np.sin(xx * 0.05 + yy * 0.012) + 4.0 * np.sin(xx * 0.21 + yy * 0.03)
    wood = np.stack([150 + grain + yy * 0.05, 105 + grain * 0.8 + yy * 0.04, 70 + grain * 0.5], -1)
    arr = np.where((yy >= horizon)[..., None], wood, wall)
    img = Image.fromarray(np.clip(arr, 0, 255).astype(np.uint8), "RGB")
    d = ImageDraw.Draw(img)
    d.rectangle([0, horizon - 3, w, horizon + 2], fill=(96, 64, 40))  # table edge
    s = h / 480.0
    # red cube: front face, top face, side face
    cx, cy, e = int(0.30 * w), int(0.66 * h), int(70 * s)
    d.ellipse([cx - e // 2, cy + e - 12 * s, cx + e * 1.2, cy + e + 14 * s], fill=(110, 75, 50))  # shadow
    d.polygon([(cx, cy), (cx + e, cy), (cx + e, cy + e), (cx, cy + e)], fill=(200, 30, 35))
    d.polygon([(cx, cy), (cx + 0.3 * e, cy - 0.3 * e), (cx + 1.3 * e, cy - 0.3 * e), (cx + e, cy)], fill=(235, 70, 70))
    d.polygon([(cx + e, cy), (cx + 1.3 * e, cy - 0.3 * e), (cx + 1.3 * e, cy + 0.7 * e), (cx + e, cy + e)], fill=(150, 20, 25))
    # blue bowl
    bx, by, bw, bh = int(0.66 * w), int(0.70 * h), int(150 * s), int(50 * s)
    d.ellipse([bx - bw // 2 - 6, by + bh // 2, bx + bw // 2 + 10, by + int(1.5 * bh)], fill=(110, 75, 50))
    d.chord([bx - bw // 2, by - bh // 2, bx + bw // 2, by + int(1.6 * bh)], 0, 180, fill=(30, 70, 170))
    d.ellipse([bx - bw // 2, by - bh // 2, bx + bw // 2, by + bh // 2], fill=(60, 110, 210))
    d.ellipse([bx - bw // 2 + 10, by - bh // 2 + 6, bx + bw // 2 - 10, by + bh // 2 - 4], fill=(20, 45, 120))
    # gripper fingers coming from the top of the frame
    gx = int(0.47 * w)
    d.rectangle([gx - 40 * s, 0, gx + 40 * s, 70 * s], fill=(70, 72, 78))
    d.rectangle([gx - 36 * s, 70 * s, gx - 22 * s, 150 * s], fill=(95, 97, 104))
    d.rectangle([gx + 22 * s, 70 * s, gx + 36 * s, 150 * s], fill=(95, 97, 104))
    return img


def decode_image(path: Path) -> np.ndarray:
    """Decodes the way a server does: PIL, convert('RGB'), uint8 HWC."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def to_model_image(batch_u8: np.ndarray) -> torch.Tensor:
    """uint8 [B,H,W,3] -> float32 [B,3,H,W] in [0,1] (a true division by 255, not a multiply)."""
    return torch.from_numpy(batch_u8).permute(0, 3, 1, 2).contiguous().to(torch.float32) / 255.0


# ----------------------------------------------------------------------------------------------
# Running upstream with probes on its modules


class Probes:
    """Instance-level wrappers around upstream methods: they record inputs/outputs and call through."""

    def __init__(self, policy: SmolVLAPolicy):
        self.model = policy.model
        self.vwe = policy.model.vlm_with_expert
        self.images_in: list[torch.Tensor] = []
        self.vision_out: list[torch.Tensor] = []
        self.prefix = None
        self.state = None
        self.kv = None
        self.velocities: list[torch.Tensor] = []
        self._wrap()

    def _wrap(self):
        vwe, model = self.vwe, self.model
        orig_embed_image = vwe.embed_image
        orig_forward = vwe.forward
        orig_embed_prefix = model.embed_prefix
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

        def sample_actions(images, img_masks, lang_tokens, lang_masks, state, *args, **kwargs):
            self.state = state.detach().clone()
            return orig_sample(images, img_masks, lang_tokens, lang_masks, state, *args, **kwargs)

        def forward(*args, **kwargs):
            out = orig_forward(*args, **kwargs)
            embeds = kwargs.get("inputs_embeds")
            if self.kv is None and embeds is not None and embeds[1] is None:
                cache = out[1]
                self.kv = [
                    (layer.keys.detach().transpose(1, 2).contiguous(), layer.values.detach().transpose(1, 2).contiguous())
                    for layer in cache.layers
                ]
            return out

        def denoise_step(*args, **kwargs):
            v = orig_denoise(*args, **kwargs)
            self.velocities.append(v.detach().clone())
            return v

        vwe.embed_image = embed_image
        vwe.forward = forward
        model.embed_prefix = embed_prefix
        model.sample_actions = sample_actions
        model.denoise_step = denoise_step


def run_upstream(ckpt: Path, images: dict[str, np.ndarray], state: np.ndarray, instructions: list[str], noise: torch.Tensor):
    """Loads the checkpoint with upstream loaders and runs pre-processor, policy and post-processor."""
    cfg, policy, pre, post = load_checkpoint(ckpt)
    probes = Probes(policy)
    batch = {key: to_model_image(arr) for key, arr in images.items()}
    batch["observation.state"] = torch.from_numpy(state)
    batch["task"] = list(instructions)
    with working_dir(ckpt), torch.no_grad():
        processed = pre(batch)
        actions_norm = policy.predict_action_chunk(processed, noise=noise.clone())
        actions = post(actions_norm)
    return cfg, policy, pre, processed, probes, actions_norm, actions


_ST_DTYPES = {
    torch.float32: "F32",
    torch.float16: "F16",
    torch.bfloat16: "BF16",
    torch.int64: "I64",
    torch.int32: "I32",
    torch.uint8: "U8",
    torch.bool: "BOOL",
}


def write_safetensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    """safetensors writer with a sorted header, so regenerating identical data gives identical bytes
    (the stock writer's header order varies from run to run)."""
    header: dict[str, object] = {"__metadata__": dict(sorted(metadata.items()))}
    blobs, offset = [], 0
    for name in sorted(tensors):
        t = tensors[name].detach().contiguous().cpu()
        raw = t.view(torch.uint8).numpy().tobytes() if t.numel() else b""
        header[name] = {"dtype": _ST_DTYPES[t.dtype], "shape": list(t.shape), "data_offsets": [offset, offset + len(raw)]}
        blobs.append(raw)
        offset += len(raw)
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)
    with open(path, "wb") as f:
        f.write(len(head).to_bytes(8, "little"))
        f.write(head)
        for raw in blobs:
            f.write(raw)


def versions() -> dict:
    import numpy

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "transformers": transformers.__version__,
        "lerobot": getattr(lerobot, "__version__", "unknown"),
        "tokenizers": tokenizers.__version__,
        "numpy": numpy.__version__,
        "safetensors": safetensors.__version__,
    }


# ----------------------------------------------------------------------------------------------
# Fixture cases

TINY_TEXT = dict(
    hidden_size=64,
    intermediate_size=128,
    num_hidden_layers=4,
    num_attention_heads=4,
    num_key_value_heads=2,
    head_dim=16,
    rms_norm_eps=1e-5,
)
TINY_VISION = dict(
    hidden_size=32,
    intermediate_size=64,
    num_hidden_layers=2,
    num_attention_heads=2,
    patch_size=8,
    image_size=64,
    layer_norm_eps=1e-6,
)
TINY_BASE_VOCAB = 384

INSTR_SHORT = "pick up the red cube"
INSTR_LONG = "Place the 2 blue blocks, then stack 3 more on top of the tray (carefully!)"
INSTR_TRUNC = (
    "First look at the table, find the 4 green cups and the 12 red plates; then put every cup on a plate, "
    "starting with the one nearest to the left edge, and finally push the tray 25 cm forward."
)

CASES = {
    "cam1_stats": dict(
        desc="1 camera (96x128 PNG), state/action 6, MEAN_STD stats, 4 VLM + 4 expert layers, chunk 8, 4 steps, fp32",
        seed=1000,
        weights_seed=11,
        cameras=[("observation.images.camera1", (96, 128), "png")],
        state_dim=6,
        action_dim=6,
        norm="MEAN_STD",
        stats=True,
        chunk_size=8,
        num_steps=4,
        num_expert_layers=-1,
        self_attn_every_n_layers=2,
        dtype=torch.float32,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam1_nostats": dict(
        desc="cam1_stats' model (same weights) saved without dataset stats",
        seed=1001,
        weights_seed=11,
        cameras=[("observation.images.camera1", (96, 128), "png")],
        state_dim=6,
        action_dim=6,
        norm="MEAN_STD",
        stats=False,
        chunk_size=8,
        num_steps=4,
        num_expert_layers=-1,
        self_attn_every_n_layers=2,
        dtype=torch.float32,
        instructions=[INSTR_LONG, INSTR_SHORT],
    ),
    "cam3_stats": dict(
        desc=(
            "3 cameras (96x128 PNG, 64x64 JPEG, 120x80 portrait PNG), state/action 7, MIN_MAX stats with one "
            "degenerate (max==min) dimension, chunk 8, 4 steps, fp32"
        ),
        seed=2000,
        weights_seed=11,
        cameras=[
            ("observation.images.camera1", (96, 128), "png"),
            ("observation.images.camera2", (64, 64), "jpg"),
            ("observation.images.camera3", (120, 80), "png"),
        ],
        state_dim=7,
        action_dim=7,
        norm="MIN_MAX",
        stats=True,
        chunk_size=8,
        num_steps=4,
        num_expert_layers=-1,
        self_attn_every_n_layers=2,
        dtype=torch.float32,
        instructions=[INSTR_SHORT, INSTR_LONG],
    ),
    "cam3_nostats": dict(
        desc=(
            "cam3_stats without stats; item 1's instruction is longer than "
            "tokenizer_max_length (48) so it is truncated"
        ),
        seed=2001,
        weights_seed=11,
        cameras=[
            ("observation.images.camera1", (96, 128), "png"),
            ("observation.images.camera2", (64, 64), "jpg"),
            ("observation.images.camera3", (120, 80), "png"),
        ],
        state_dim=7,
        action_dim=7,
        norm="MIN_MAX",
        stats=False,
        chunk_size=8,
        num_steps=4,
        num_expert_layers=-1,
        self_attn_every_n_layers=2,
        dtype=torch.float32,
        instructions=[INSTR_LONG, INSTR_TRUNC],
    ),
    "cam2_bf16_fewer_expert_layers": dict(
        desc=(
            "2 cameras (80x80 PNG, 72x96 JPEG), model.safetensors in bfloat16, VLM config with 6 text layers "
            "truncated to num_vlm_layers 4, 2 expert layers (one per 2 VLM layers), self_attn_every_n_layers 4 (only layer 0 "
            "self-attention), chunk 10, 5 steps, MEAN_STD stats, state 5 / action 4"
        ),
        text_layers=6,
        num_vlm_layers=4,
        seed=3000,
        weights_seed=33,
        cameras=[
            ("observation.images.wrist", (80, 80), "png"),
            ("observation.images.top", (72, 96), "jpg"),
        ],
        state_dim=5,
        action_dim=4,
        norm="MEAN_STD",
        stats=True,
        chunk_size=10,
        num_steps=5,
        num_expert_layers=2,
        # With fewer expert layers upstream only runs when layer 0 is the sole self-attention layer: the
        # expert picks cross/self K/V projections by expert index while the forward picks the mode by VLM
        # index (shape error for every-2), and a VLM layer without an expert layer in self-attention mode
        # fails during denoising (every-3).
        self_attn_every_n_layers=4,
        dtype=torch.bfloat16,
        instructions=[INSTR_LONG, INSTR_SHORT],
    ),
}


def stats_note(stats_present: bool, norm: str) -> str:
    if stats_present:
        if norm == "MEAN_STD":
            how = "state: (x - mean) / (std + 1e-8); action out: y * std + mean (no eps)"
        else:
            how = (
                "state: 2 * (x - min) / d - 1 and action out: (y + 1) / 2 * d + min, "
                "with d = max - min replaced by 1e-8 where it is 0"
            )
        return f"present ({norm}); {how}; images are IDENTITY (their stats are stored but unused)"
    return (
        "absent: the normalizer/unnormalizer steps are saved with no state file and pass state and "
        "actions through unchanged (identity), although normalization_mapping still says "
        f"{norm}; out.actions == out.actions_normalized"
    )


def write_images(case_dir: Path, cameras, batch: int, seed: int) -> tuple[dict, dict]:
    inputs = case_dir / "inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    images, files = {}, {}
    for ci, (key, (h, w), fmt) in enumerate(cameras):
        short = key.split(".")[-1]
        arrs, names = [], []
        for b in range(batch):
            img = draw_scene(h, w, seed * 100 + ci * 10 + b)
            name = f"{short}_{b}.{fmt}"
            if fmt == "jpg":
                img.save(inputs / name, format="JPEG", quality=90)
            else:
                img.save(inputs / name, format="PNG", optimize=True)
            arrs.append(decode_image(inputs / name))
            names.append(name)
        images[key] = np.stack(arrs)
        files[key] = names
    return images, files


def run_case(name: str, spec: dict, out_root: Path, tiny_tok: Tokenizer) -> Path:
    case_dir = out_root / name
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    B = 2
    cameras = spec["cameras"]
    cfg = make_config(
        cameras=[(k, hw) for k, hw, _ in cameras],
        state_dim=spec["state_dim"],
        action_dim=spec["action_dim"],
        norm=spec["norm"],
        chunk_size=spec["chunk_size"],
        num_steps=spec["num_steps"],
        num_vlm_layers=spec.get("num_vlm_layers", TINY_TEXT["num_hidden_layers"]),
        num_expert_layers=spec["num_expert_layers"],
        self_attn_every_n_layers=spec["self_attn_every_n_layers"],
        resize=(TINY_VISION["image_size"], TINY_VISION["image_size"]),
    )
    gen = np.random.default_rng(spec["seed"])
    stats = make_stats(cfg, np.random.default_rng(spec["weights_seed"] + 7), degenerate_dim=spec["norm"] == "MIN_MAX")
    ckpt = case_dir / "checkpoint"
    build_checkpoint(
        ckpt,
        cfg,
        seed=spec["weights_seed"],
        text={**TINY_TEXT, "num_hidden_layers": spec.get("text_layers", TINY_TEXT["num_hidden_layers"])},
        vision=TINY_VISION,
        scale_factor=2,
        tok=tiny_tok,
        stats=stats if spec["stats"] else None,
        dtype=spec["dtype"],
    )
    images, files = write_images(case_dir, cameras, B, spec["seed"])
    sd, ad = spec["state_dim"], spec["action_dim"]
    st = stats["observation.state"]
    state = (st["mean"][None, :] + gen.normal(0, 1, (B, sd)).astype(np.float32) * np.maximum(st["std"], 1.0)[None, :]).astype(np.float32)
    if spec["norm"] == "MIN_MAX":
        state[:, -1] = st["min"][-1]  # the degenerate dim sits exactly on its single dataset value
    noise = torch.from_numpy(gen.standard_normal((B, cfg.chunk_size, cfg.max_action_dim)).astype(np.float32))

    record_oracle(case_dir, ckpt, images, files, state, noise, spec, generator="tools/oracle/smolvla_oracle.py fixtures")
    return case_dir


def record_oracle(
    case_dir: Path, ckpt: Path, images: dict, files: dict, state: np.ndarray, noise: torch.Tensor, spec: dict, *,
    generator: str, extra_meta: dict | None = None,
) -> None:
    """Runs upstream on `ckpt` and writes `case_dir/oracle.safetensors`: inputs, intermediates, outputs."""
    cfg_loaded, policy, pre, processed, probes, actions_norm, actions = run_upstream(
        ckpt, images, state, spec["instructions"], noise
    )
    keys = [k for k in cfg_loaded.image_features]
    assert len(probes.images_in) == len(keys) and probes.kv is not None and probes.prefix is not None
    param_dtypes = sorted({str(p.dtype) for p in policy.parameters()})
    n_layers = policy.model.vlm_with_expert.num_vlm_layers

    t: dict[str, torch.Tensor] = {
        "input.state": torch.from_numpy(state),
        "input.noise": noise,
    }
    for key in keys:
        t[f"input.image.{key}"] = torch.from_numpy(images[key])
    for key, img, vis in zip(keys, probes.images_in, probes.vision_out, strict=True):
        t[f"pre.pixels.{key}"] = img.float()
        t[f"mid.vision.{key}"] = vis.float()
    t["pre.lang_tokens"] = processed["observation.language.tokens"].to(torch.int64)
    t["pre.lang_mask"] = processed["observation.language.attention_mask"].to(torch.uint8)
    t["pre.state"] = probes.state.float()
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

    tok = AutoTokenizer.from_pretrained(str(ckpt / "vlm"))
    meta = {
        "versions": json.dumps(versions()),
        "instructions": json.dumps(spec["instructions"]),
        "cameras": json.dumps(keys),
        "input_files": json.dumps(files),
        "case": spec["desc"],
        "stats": stats_note(spec["stats"], spec["norm"]),
        "seed": json.dumps({"inputs": spec["seed"], "weights": spec["weights_seed"]}),
        "checkpoint_param_dtype_after_load": ",".join(param_dtypes),
        "tokenizer": json.dumps(
            {
                "class": type(tok).__name__,
                "pad_token": tok.pad_token,
                "pad_token_id": tok.pad_token_id,
                "padding": cfg_loaded.pad_language_to,
                "padding_side": "right",
                "truncation_side": tok.truncation_side,
                "max_length": cfg_loaded.tokenizer_max_length,
                "effective_pre_tokenizer": tok.backend_tokenizer.pre_tokenizer.__getstate__().decode()
                if hasattr(tok.backend_tokenizer.pre_tokenizer, "__getstate__")
                else str(tok.backend_tokenizer.pre_tokenizer),
                "task_suffix": "\\n appended when missing",
            }
        ),
        "config": json.dumps(
            {
                "chunk_size": cfg_loaded.chunk_size,
                "num_steps": cfg_loaded.num_steps,
                "max_state_dim": cfg_loaded.max_state_dim,
                "max_action_dim": cfg_loaded.max_action_dim,
                "num_vlm_layers": n_layers,
                "num_expert_layers": policy.model.vlm_with_expert.num_expert_layers,
                "self_attn_every_n_layers": cfg_loaded.self_attn_every_n_layers,
                "resize_imgs_with_padding": list(cfg_loaded.resize_imgs_with_padding),
            }
        ),
        "generator": generator,
        **(extra_meta or {}),
    }
    write_safetensors(case_dir / "oracle.safetensors", t, meta)
    check = safetensors.safe_open(str(case_dir / "oracle.safetensors"), "pt")
    assert set(check.keys()) == set(t) and all(torch.equal(check.get_tensor(k), t[k]) for k in t)


def cmd_fixtures(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = args.cases.split(",") if args.cases else list(CASES)
    tiny_tok = train_tokenizer(TINY_BASE_VOCAB)
    for name in names:
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
        d = run_case(name, CASES[name], out, tiny_tok)
        print(f"wrote {d}")


# ----------------------------------------------------------------------------------------------
# Full-size random-weight checkpoint (benchmarks) and the demo policy

FULL_TEXT = dict(
    hidden_size=960,
    intermediate_size=2560,
    num_hidden_layers=32,
    num_attention_heads=15,
    num_key_value_heads=5,
    head_dim=64,
    rms_norm_eps=1e-5,
)
FULL_VISION = dict(
    hidden_size=768,
    intermediate_size=3072,
    num_hidden_layers=12,
    num_attention_heads=12,
    patch_size=16,
    image_size=512,
    layer_norm_eps=1e-6,
)


def cmd_full_size(args) -> None:
    out = Path(args.out)
    cfg = make_config(
        cameras=[(f"observation.images.camera{i}", (512, 512)) for i in (1, 2, 3)],
        state_dim=6,
        action_dim=6,
        norm="MEAN_STD",
        chunk_size=50,
        num_steps=10,
        num_vlm_layers=16,
        num_expert_layers=-1,
        self_attn_every_n_layers=2,
        resize=(512, 512),
        tokenizer_max_length=48,
        expert_width_multiplier=0.75,
    )
    cfg.n_action_steps = 50
    tok = train_tokenizer(TINY_BASE_VOCAB, fill_to=49152)
    assert tok.get_vocab_size(with_added_tokens=True) == 49280
    stats = make_stats(cfg, np.random.default_rng(5), degenerate_dim=False)
    build_checkpoint(
        out, cfg, seed=5, text=FULL_TEXT, vision=FULL_VISION, scale_factor=4, tok=tok, stats=stats,
        dtype=torch.bfloat16,
    )
    (out / "README.md").write_text(
        "Random-weight SmolVLA checkpoint with SmolVLM2-500M / lerobot smolvla_base shapes, for benchmarks only.\n"
        "Generated by `tools/oracle/run.sh smolvla_oracle.py full-size`; the tokenizer is a synthetic byte-level "
        "BPE padded to the real vocabulary size (49280), so token ids differ from the real model's.\n"
    )
    print(f"wrote {out}")


def cmd_demo(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "smolvla-demo"
    cfg = make_config(
        cameras=[("observation.images.front", (480, 640))],
        state_dim=6,
        action_dim=6,
        norm="MEAN_STD",
        chunk_size=50,
        num_steps=10,
        num_vlm_layers=TINY_TEXT["num_hidden_layers"],
        num_expert_layers=-1,
        self_attn_every_n_layers=2,
        resize=(TINY_VISION["image_size"], TINY_VISION["image_size"]),
    )
    # an SO-100 style arm: five joints in degrees and a gripper opening in percent
    stats = {
        "observation.state": {
            "mean": np.array([0.0, 90.0, 90.0, 45.0, 0.0, 20.0], np.float32),
            "std": np.array([30.0, 25.0, 25.0, 20.0, 40.0, 15.0], np.float32),
            "min": np.array([-90.0, 20.0, 10.0, -30.0, -150.0, 0.0], np.float32),
            "max": np.array([90.0, 170.0, 180.0, 110.0, 150.0, 60.0], np.float32),
        },
    }
    stats["action"] = {k: v.copy() for k, v in stats["observation.state"].items()}
    stats["observation.images.front"] = {
        "mean": np.array([0.45, 0.42, 0.40], np.float32).reshape(3, 1, 1),
        "std": np.array([0.22, 0.22, 0.23], np.float32).reshape(3, 1, 1),
        "min": np.zeros((3, 1, 1), np.float32),
        "max": np.ones((3, 1, 1), np.float32),
    }
    tok = train_tokenizer(TINY_BASE_VOCAB)
    build_checkpoint(
        ckpt, cfg, seed=42, text=TINY_TEXT, vision=TINY_VISION, scale_factor=2, tok=tok, stats=stats,
        dtype=torch.float32,
    )
    sample = draw_demo_scene(480, 640)
    sample.save(out / "sample.png", format="PNG", optimize=True)
    # prove the demo loads and runs through upstream
    img = decode_image(out / "sample.png")[None]
    state = stats["observation.state"]["mean"][None, :].copy()
    noise = torch.from_numpy(np.random.default_rng(0).standard_normal((1, 50, 32)).astype(np.float32))
    _, _, _, _, _, _, actions = run_upstream(ckpt, {"observation.images.front": img}, state, ["pick up the red cube"], noise)
    print(f"wrote {ckpt}; sample chunk shape {tuple(actions.shape)}, first action {actions[0, 0].tolist()}")


def main(argv: list[str] | None = None) -> None:
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fixtures")
    f.add_argument("--out", default=str(REPO_ROOT / "tests" / "fixtures" / "smolvla"))
    f.add_argument("--cases", default="")
    fs = sub.add_parser("full-size")
    fs.add_argument("--out", default=str(CACHE / "checkpoints" / "smolvla-full-random"))
    d = sub.add_parser("demo")
    d.add_argument("--out", default=str(REPO_ROOT / "models" / "demo"))
    args = p.parse_args(argv)
    {"fixtures": cmd_fixtures, "full-size": cmd_full_size, "demo": cmd_demo}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
