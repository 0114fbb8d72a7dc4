"""FluxVLA-layout run directories built from the tiny lerobot pi0.5 fixtures, and what FluxVLA's code makes of them.

FluxVLA (limxdynamics/FluxVLA) is not on PyPI and needs CUDA, LIBERO and TensorFlow for its evaluation, so it is not
run here. Instead this script:

1. writes a directory as FluxVLA's trainer leaves it (scripts/train.py _save_resolved_config and
   save_dataset_statistics, fsdp_train_runner.py save_checkpoint, PaligemmaTokenizer.save_pretrained): config.json /
   config.yaml (the resolved mmengine config of configs/pi05/pi05_paligemma_libero_10_full_finetune.py with the tiny
   sizes), checkpoints/step-*.safetensors (the lerobot fixture's tensors under FluxVLA's flat PI05FlowMatching names:
   the inverse of the prefix renames, plus the expert's unused embed_tokens), dataset_statistics.json,
   llm_backbone_config.json and tokenizer/{tokenizer.model, tokenizer_config.json};
2. restates, from reading FluxVLA's source at c6cd5a060f52dd083110dda798f3f88e96cf8c42, what its LIBERO evaluation
   does around the network: TransformImage, PaligemmaTokenizer.tokenize + LiberoPromptFromInputs padding (run with
   the real libsentencepiece on the saved tokenizer.model), LiberoProprioFromInputs' state normalisation,
   predict_action's prefix / float32 Euler loop, the float32 create_sinusoidal_pos_embedding, and
   DenormalizeLiberoAction (with its gripper mapping);
3. runs the network itself with lerobot's PI05Pytorch on the fixture's weights (FluxVLA's PI05FlowMatching is the
   same network: same modules, masks, positions, adaRMS and time MLP; read, not run), fed by those restatements, and
   records inputs, intermediates and outputs as tests/fixtures/pi05_fluxvla/<case>/oracle.safetensors.

Sub-commands:
  fixtures [--out DIR] [--cases a,b]    the cases below
  tokenizer [--out FILE]                tests/fixtures/pi05_fluxvla/tokenizer_cases.json: FluxVLA's prompt ids
                                        (libsentencepiece) for robot tasks and edge cases
"""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import pi_oracle  # noqa: E402  (sets HF_HUB_CACHE before any Hugging Face import)

import numpy as np  # noqa: E402
import safetensors.torch  # noqa: E402
import sentencepiece  # noqa: E402
import torch  # noqa: E402
import transformers  # noqa: E402
import yaml  # noqa: E402
from PIL import Image  # noqa: E402
from lerobot.policies.pi05 import modeling_pi05  # noqa: E402

from smolvla_oracle import versions, write_images, write_safetensors  # noqa: E402

REPO_ROOT = pi_oracle.REPO_ROOT
FIXTURES = REPO_ROOT / "tests" / "fixtures" / "pi05_fluxvla"
TOKENIZER_MODEL = (
    pi_oracle.HUB_CACHE
    / ("models--" + pi_oracle.paligemma_tokenizer.REPO_ID.replace("/", "--"))
    / "snapshots"
    / pi_oracle.paligemma_tokenizer.REVISION
    / "tokenizer.model"
)
FLUXVLA = "limxdynamics/FluxVLA@c6cd5a060f52dd083110dda798f3f88e96cf8c42"
GENERATOR = "tools/oracle/fluxvla_oracle.py fixtures"

# What each restatement below follows (FV = FluxVLA at the commit above).
RESTATES = {
    "layout": "FV:scripts/train.py:118-127,303-321; FV:fluxvla/engines/runners/fsdp_train_runner.py:135-250; "
    "FV:fluxvla/engines/runners/base_train_runner.py:442-456; FV:fluxvla/tokenizers/paligemma_tokenizer.py:77-101; "
    "FV:fluxvla/datasets/utils/data_utils.py:626-657; FV:fluxvla/datasets/dataset_wrapper.py:239-405",
    "parameter names": "FV:fluxvla/models/vlas/pi0_flowmatching.py:76-170 (modules), "
    "FV:fluxvla/models/backbones/visions/siglip_vit.py:39-50 (vision_backbone.vision = SiglipVisionModel), "
    "FV:fluxvla/models/projectors/linear_projector.py (.projector), "
    "FV:fluxvla/models/backbones/llms/condition_gemma.py:697-823 (ConditionGemmaModel), "
    "FV:configs/pi05/pi05_paligemma_libero_10_full_finetune.py:104-116 (name_mapping)",
    "images": "FV:fluxvla/transforms/transform_images.py:414-548 (TransformImage, resize-naive): PIL bilinear resize "
    "(a copy at the same size), centre crop, float32 pixels, (x - mean) / std with float64 mean/std, then .float()",
    "prompt": "FV:fluxvla/tokenizers/paligemma_tokenizer.py:51-71 (strip, '_' and '\\n' -> ' ', "
    "sp.encode(text, add_bos=True) + sp.encode('\\n')); FV:fluxvla/transforms/transform_prompts.py:349-400 "
    "(LiberoPromptFromInputs: prompt = task, right-padded with 0 / mask False to max_len, or cut to max_len)",
    "state": "FV:fluxvla/transforms/normalize.py:486-531 (LiberoProprioFromInputs: (x - mean) / (std + 1e-6) in "
    "float64, zero-padded to state_dim); the network never reads it (FV:fluxvla/models/vlas/pi05_flowmatching.py:68-127)",
    "network": "FV:fluxvla/models/vlas/pi0_flowmatching.py:204-250 (embed_prefix), 702-831 (predict_action, "
    "denoise_step), FV:fluxvla/models/vlas/pi05_flowmatching.py:68-127 (embed_suffix): run as lerobot 0.6.1's "
    "PI05Pytorch.embed_prefix / paligemma_with_expert.forward / denoise_step, the same computation",
    "time": "FV:fluxvla/models/vlas/pi0_flowmatching.py:642-649 (time = float32 1.0, dt = float32 -1/num_steps, "
    "while time >= -dt / 2: x += dt * v; time += dt) and FV:fluxvla/engines/utils/model_utils.py:40-68 "
    "(create_sinusoidal_pos_embedding in float32), patched into lerobot's embed_suffix",
    "actions": "FV:fluxvla/transforms/normalize.py:143-192 (DenormalizeLiberoAction: a[..., :action_dim] * std + mean "
    "in float64) and FV:fluxvla/engines/utils/robot_utils.py:18-58 (gripper: 2g - 1, sign, negate) for out.actions_libero",
}

# FluxVLA's LIBERO image statistics (ImageNet's, x 255, as the config writes them).
LIBERO_MEAN = [123.515625, 116.04492188, 103.59375]
LIBERO_STD = [58.27148438, 57.02636719, 57.27539062]

LIBERO_TASK = "put both the alphabet soup and the tomato sauce in the basket"
UNDERSCORE_TASK = " open_the_drawer and\nput the sponge inside\n"
LONG_TASK = "Place the 2 blue blocks, then stack 3 more on top of the tray (carefully!) and wait"

CASES = {
    "libero_f32": dict(
        desc=(
            "the LIBERO-10 config's structure and values (2 cameras agentview + wrist, FluxVLA's ImageNet x 255 "
            "mean/std, max_len 180, MEAN_STD statistics with q01/q99, statistic name libero_10_no_noops) on the "
            "float32 weights of pi05/cam1_quantiles_bins; chunk 8, 4 steps, 56 px; an older, broken step file "
            "beside the newest"
        ),
        source="pi05/cam1_quantiles_bins",
        tiny=pi_oracle.TINY_A,
        chunk=8,
        steps=4,
        max_action_dim=32,
        resolution=56,
        cameras=[("observation.images.image", "png"), ("observation.images.wrist_image", "png")],
        means=[LIBERO_MEAN, LIBERO_MEAN],
        stds=[LIBERO_STD, LIBERO_STD],
        max_len=180,
        with_quantiles=True,
        decoy_step=True,
        extra_stats_entry=False,
        instructions=[LIBERO_TASK, UNDERSCORE_TASK],
        seed=7100,
    ),
    "variant_bf16": dict(
        desc=(
            "the bfloat16 weights of pi05/variant_dims (3 + 3 layers, expert width 48, 2 SigLIP layers, 112 px), "
            "chunk 12, 3 steps, max_action_dim 24; cameras in the other order (wrist first) with a different "
            "mean/std per camera; max_len 16, so the long task loses its end and the newline; q01/q99 null; "
            "dataset_statistics.json with a second entry the loader must not pick"
        ),
        source="pi05/variant_dims",
        tiny=pi_oracle.TINY_B,
        chunk=12,
        steps=3,
        max_action_dim=24,
        resolution=112,
        cameras=[("observation.images.wrist_image", "jpg"), ("observation.images.image", "png")],
        means=[[110.0, 100.5, 90.25], LIBERO_MEAN],
        stds=[[60.0, 55.5, 50.125], LIBERO_STD],
        max_len=16,
        with_quantiles=False,
        decoy_step=False,
        extra_stats_entry=True,
        instructions=[LONG_TASK, "pick up the red cube"],
        seed=7200,
    ),
}

STATE_DIM, ACTION_DIM, STATS_NAME = 8, 7, "libero_10_no_noops"

# lerobot PI05Policy prefix -> FluxVLA PI05FlowMatching prefix (the inverse of Tether's loader table).
TO_FLUXVLA = [
    ("model.paligemma_with_expert.paligemma.model.vision_tower.", "vision_backbone.vision."),
    ("model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear.", "projector.projector."),
    ("model.paligemma_with_expert.paligemma.model.language_model.", "llm_backbone."),
    ("model.paligemma_with_expert.gemma_expert.model.", "llm_expert."),
    ("model.action_in_proj.", "action_in_proj.projector."),
    ("model.action_out_proj.", "action_out_proj.projector."),
    ("model.time_mlp_in.", "time_mlp_in.projector."),
    ("model.time_mlp_out.", "time_mlp_out.projector."),
]
LERO_LM_HEADS = ("model.paligemma_with_expert.paligemma.lm_head.weight", "model.paligemma_with_expert.gemma_expert.lm_head.weight")


# ----------------------------------------------------------------------------------------------
# The run directory


def fluxvla_state_dict(lerobot: dict[str, torch.Tensor], expert_vocab: int, expert_width: int, seed: int) -> dict:
    out = {}
    for name, t in lerobot.items():
        if name in LERO_LM_HEADS:
            continue  # PaliGemma's lm_head is the tied embedding; the expert's has no FluxVLA counterpart
        for src, dst in TO_FLUXVLA:
            if name.startswith(src):
                out[dst + name[len(src):]] = t.clone()
                break
        else:
            raise RuntimeError(f"{name}: no FluxVLA counterpart")
    # ConditionGemmaModel builds embed_tokens for the expert too; FluxVLA saves it, never reads it.
    gen = torch.Generator().manual_seed(seed)
    dtype = out["llm_expert.norm.dense.weight"].dtype
    out["llm_expert.embed_tokens.weight"] = (torch.randn(expert_vocab, expert_width, generator=gen) * 0.02).to(dtype)
    return out


def gemma_fields(cfg, *, adarms: int | None) -> dict:
    """ConditionGemmaModel's dict in FluxVLA's config, sizes from the fixture's GemmaConfig."""
    d = dict(
        type="ConditionGemmaModel",
        adarms_cond_dim=adarms,
        attention_bias=False,
        attention_dropout=0.0,
        bos_token_id=2,
        eos_token_id=1,
        head_dim=cfg.head_dim,
        hidden_act="gelu_pytorch_tanh",
        hidden_activation="gelu_pytorch_tanh",
        hidden_size=cfg.hidden_size,
        initializer_range=0.02,
        intermediate_size=cfg.intermediate_size,
        max_position_embeddings=8192,
        model_type="gemma",
        num_attention_heads=cfg.num_attention_heads,
        num_hidden_layers=cfg.num_hidden_layers,
        num_key_value_heads=cfg.num_key_value_heads,
        rms_norm_eps=1e-06,
        rope_theta=10000.0,
        torch_dtype="float32",
        use_cache=True,
        vocab_size=cfg.vocab_size,
    )
    if adarms is not None:
        d.update(pad_token_id=0, transformers_version="4.48.1", use_adarms=True)
    return d


def fluxvla_config(spec: dict, vlm_cfg, expert_cfg, vision_cfg) -> dict:
    """The resolved config as FluxVLA dumps it: the LIBERO-10 fine-tune config with the fixture's sizes."""
    cams = [key for key, _ in spec["cameras"]]
    R = spec["resolution"]
    return {
        "model": dict(
            type="PI05FlowMatching",
            llm_backbone=gemma_fields(vlm_cfg, adarms=None),
            vision_backbone=dict(
                type="SigLIPViTBackbone",
                vision_backbone_id="siglip_224",
                vision_config=dict(
                    attention_dropout=0.0,
                    hidden_act="gelu_pytorch_tanh",
                    hidden_size=vision_cfg.hidden_size,
                    image_size=R,
                    intermediate_size=vision_cfg.intermediate_size,
                    layer_norm_eps=1e-06,
                    model_type="siglip_vision_model",
                    num_attention_heads=vision_cfg.num_attention_heads,
                    num_channels=3,
                    num_hidden_layers=vision_cfg.num_hidden_layers,
                    patch_size=vision_cfg.patch_size,
                    projection_dim=vlm_cfg.hidden_size,
                    projector_hidden_act="gelu_fast",
                    torch_dtype="float32",
                    vision_use_head=False,
                ),
            ),
            projector=dict(type="LinearProjector", in_dim=vision_cfg.hidden_size, out_dim=vlm_cfg.hidden_size),
            proj_width=expert_cfg.hidden_size,
            n_action_steps=spec["chunk"],
            num_steps=spec["steps"],
            action_in_proj=dict(type="LinearProjector", in_dim=spec["max_action_dim"], out_dim=expert_cfg.hidden_size),
            action_out_proj=dict(type="LinearProjector", in_dim=expert_cfg.hidden_size, out_dim=spec["max_action_dim"]),
            time_mlp_in=dict(type="LinearProjector", in_dim=expert_cfg.hidden_size, out_dim=expert_cfg.hidden_size),
            time_mlp_out=dict(type="LinearProjector", in_dim=expert_cfg.hidden_size, out_dim=expert_cfg.hidden_size),
            max_action_dim=spec["max_action_dim"],
            llm_expert=gemma_fields(expert_cfg, adarms=expert_cfg.hidden_size),
            freeze_llm_backbone=False,
            freeze_vision_backbone=False,
            pretrained_name_or_path="./checkpoints/pi05_libero/model.safetensors",
            name_mapping={
                "llm_backbone": "paligemma_with_expert.paligemma.model.language_model",
                "vision_backbone.vision": "paligemma_with_expert.paligemma.model.vision_tower",
                "projector.projector": "paligemma_with_expert.paligemma.model.multi_modal_projector.linear",
                "llm_expert": "paligemma_with_expert.gemma_expert.model",
                "time_mlp_in.projector": "time_mlp_in",
                "time_mlp_out.projector": "time_mlp_out",
                "action_in_proj.projector": "action_in_proj",
                "action_out_proj.projector": "action_out_proj",
                "llm_backbone.embed_tokens": "paligemma_with_expert.paligemma.lm_head",
            },
        ),
        "train_dataloader": dict(
            per_device_batch_size=8,
            per_device_num_workers=4,
            dataset=dict(
                type="DistributedRepeatingDataset",
                name_mappings={"observation.state": ["proprio"], "action": ["action"]},
                statistic_keys=["observation.state", "timestamp", "action"],
                statistic_name=STATS_NAME,
                datasets=dict(
                    type="ParquetDataset",
                    data_root_path="./datasets/libero_10_no_noops_lerobotv2.1",
                    transforms=[
                        dict(
                            type="ProcessParquetInputs",
                            parquet_keys=["observation.state", "timestamp", "actions", "info", "stats", "action_masks"],
                            video_keys=cams,
                            name_mappings={"observation.state": ["states"], "actions": ["actions"]},
                        ),
                        dict(type="ParquetPrompter", use_conversation=False),
                        dict(type="ProcessPrompts", tokenizer=dict(type="PaligemmaTokenizer"), max_len=spec["max_len"]),
                        dict(type="ResizeImages", height=R, width=R),
                        dict(type="NormalizeImages", means=spec["means"], stds=spec["stds"]),
                        dict(
                            type="NormalizeStatesAndActions",
                            action_dim=spec["max_action_dim"],
                            state_dim=32,
                            state_key="proprio",
                            action_key="action",
                            norm_type="mean_std",
                        ),
                    ],
                    action_window_size=spec["chunk"],
                    action_key="action",
                    use_delta=False,
                    statistic_name=STATS_NAME,
                    window_start_idx=0,
                ),
            ),
        ),
        "runner": dict(
            type="FSDPTrainRunner",
            max_epochs=24,
            learning_rate=5e-05,
            weight_decay=0.0,
            max_grad_norm=1.0,
            sharding_strategy="no-shard",
            tokenizer=dict(type="PaligemmaTokenizer"),
            enable_gradient_checkpointing=True,
            enable_mixed_precision_training=True,
            mixed_precision_dtype="bf16",
            change_key_name=False,
        ),
        "eval": dict(
            type="LiberoEvalRunner",
            task_suite_name="libero_10",
            model_family="pi0",
            eval_chunk_size=spec["chunk"],
            resize_size=R,
            num_trials_per_task=50,
            num_steps_wait=10,
            seed=7,
            dataset=dict(
                type="LiberoParquetEvalDataset",
                transforms=[
                    dict(type="ProcessLiberoEvalInputs", img_keys=["agentview_image", "robot0_eye_in_hand_image"]),
                    dict(
                        type="TransformImage",
                        image_resize_strategy="resize-naive",
                        input_sizes=[[3, R, R]] * len(cams),
                        means=spec["means"],
                        stds=spec["stds"],
                    ),
                    dict(
                        type="LiberoPromptFromInputs",
                        use_conversation=False,
                        tokenizer=dict(type="PaligemmaTokenizer"),
                        max_len=spec["max_len"],
                    ),
                    dict(
                        type="LiberoProprioFromInputs",
                        norm_type="mean_std",
                        pos_key="robot0_eef_pos",
                        quat_key="robot0_eef_quat",
                        gripper_key="robot0_gripper_qpos",
                        state_dim=32,
                        out_key="states",
                    ),
                ],
            ),
            denormalize_action=dict(type="DenormalizeLiberoAction", norm_type="mean_std", action_dim=ACTION_DIM),
        ),
    }


def feature_stats(gen: np.random.Generator, dim: int, lo: float, hi: float, quantiles: bool) -> dict:
    """One key's entry as get_dataset_statistics writes it (lists; q01/q99 None without quantiles)."""
    mean = gen.uniform(lo, hi, dim)
    std = gen.uniform(0.05, 0.6, dim)
    return {
        "mean": mean.tolist(),
        "std": std.tolist(),
        "min": (mean - 3 * std).tolist(),
        "max": (mean + 3 * std).tolist(),
        "q01": (mean - 2.3 * std).tolist() if quantiles else None,
        "q99": (mean + 2.3 * std).tolist() if quantiles else None,
    }


def dataset_statistics(spec: dict, gen: np.random.Generator) -> dict:
    entry = {
        "proprio": feature_stats(gen, STATE_DIM, -0.5, 0.5, spec["with_quantiles"]),
        "timestamp": feature_stats(gen, 1, 5.0, 15.0, spec["with_quantiles"]),
        "action": feature_stats(gen, ACTION_DIM, -0.3, 0.3, spec["with_quantiles"]),
    }
    stats = {STATS_NAME: entry}
    if spec["extra_stats_entry"]:  # another dataset's statistics: must not be picked
        stats = {"libero_90_no_noops": {k: feature_stats(gen, len(v["mean"]), 3.0, 4.0, True) for k, v in entry.items()}, **stats}
    return stats


def write_run_dir(spec: dict, ckpt: Path, policy, gen: np.random.Generator) -> dict:
    if ckpt.exists():
        shutil.rmtree(ckpt)
    (ckpt / "checkpoints").mkdir(parents=True)
    pwe = policy.model.paligemma_with_expert
    vlm_cfg = pwe.paligemma.config.text_config
    vision_cfg = pwe.paligemma.config.vision_config
    expert_cfg = pwe.gemma_expert.config
    src = REPO_ROOT / "tests" / "fixtures" / spec["source"] / "checkpoint" / "model.safetensors"
    tensors = fluxvla_state_dict(safetensors.torch.load_file(str(src)), expert_cfg.vocab_size, expert_cfg.hidden_size, spec["seed"])
    # _save_model_safetensors: safetensors' save_file of the flat state dict, no metadata
    safetensors.torch.save_file(tensors, str(ckpt / "checkpoints" / "step-000120-epoch-03-loss=0.0170.safetensors"))
    if spec["decoy_step"]:  # an earlier save; a loader that picks it fails on its missing tensors
        safetensors.torch.save_file({"action_in_proj.projector.bias": torch.zeros(1)},
                                    str(ckpt / "checkpoints" / "step-000040-epoch-01-loss=0.5000.safetensors"))
    cfg = fluxvla_config(spec, vlm_cfg, expert_cfg, vision_cfg)
    # _save_resolved_config dumps config.yaml with draccus (not installed here: yaml.safe_dump of the same dict),
    # then config.json as json.dump(yaml.safe_load(...), indent=2)
    with open(ckpt / "config.yaml", "w") as f:
        yaml.safe_dump(cfg, f, sort_keys=False)
    with open(ckpt / "config.yaml") as fy, open(ckpt / "config.json", "w") as fj:
        json.dump(yaml.safe_load(fy), fj, indent=2)
    stats = dataset_statistics(spec, gen)
    with open(ckpt / "dataset_statistics.json", "w") as f:
        json.dump(stats, f, indent=2)
    transformers.GemmaConfig(**{k: v for k, v in cfg["model"]["llm_backbone"].items() if k != "type"}).to_json_file(
        str(ckpt / "llm_backbone_config.json")
    )
    tok = ckpt / "tokenizer"
    tok.mkdir()
    sp = sentencepiece.SentencePieceProcessor(model_file=str(TOKENIZER_MODEL))
    (tok / "tokenizer.model").write_bytes(sp.serialized_model_proto())
    with open(tok / "tokenizer_config.json", "w", encoding="utf-8") as f:
        json.dump({"tokenizer_class": "PaligemmaTokenizer", "spm_file": "tokenizer.model"}, f, ensure_ascii=False, indent=2)
    return {"config": cfg, "stats": stats[STATS_NAME]}


# ----------------------------------------------------------------------------------------------
# FluxVLA's processing, restated


def transform_image(img: np.ndarray, mean, std, size: int) -> np.ndarray:
    """TransformImage.apply_transform with resize-naive, one camera: HWC uint8 -> CHW float64."""
    pil = Image.fromarray(img).convert("RGB").resize((size, size), Image.Resampling.BILINEAR)
    left, top = (pil.width - size) // 2, (pil.height - size) // 2
    pil = pil.crop((left, top, left + size, top + size))
    x = np.array(pil).astype(np.float32)
    return ((x - np.array(mean)) / np.array(std)).transpose(2, 0, 1)


class FluxTokenizer:
    """PaligemmaTokenizer.tokenize on the saved SentencePiece model, then LiberoPromptFromInputs' pad / cut."""

    def __init__(self, model_path: Path):
        self.sp = sentencepiece.SentencePieceProcessor(model_proto=Path(model_path).read_bytes())

    def ids(self, prompt: str) -> list[int]:
        cleaned = prompt.strip().replace("_", " ").replace("\n", " ")
        return self.sp.encode(cleaned, add_bos=True) + self.sp.encode("\n")

    def padded(self, prompt: str, max_len: int, pad_id: int = 0) -> tuple[list[int], list[bool]]:
        ids = self.ids(prompt)
        mask = [True] * len(ids)
        if len(ids) < max_len:
            return ids + [pad_id] * (max_len - len(ids)), mask + [False] * (max_len - len(ids))
        return ids[:max_len], mask[:max_len]


def sinusoid_f32(time, dimension, min_period, max_period, device="cpu"):
    """create_sinusoidal_pos_embedding as FluxVLA computes it: every step in float32."""
    fraction = torch.linspace(0.0, 1.0, dimension // 2, dtype=torch.float32, device=device)
    period = min_period * (max_period / min_period) ** fraction
    angular = 1.0 / period * 2 * math.pi
    arg = time[..., None] * angular
    return torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)


def predict_action(model, images, img_masks, tokens, masks, noise, num_steps):
    """predict_action (prefix once, then the plain float32 Euler loop) on lerobot's PI05Pytorch modules."""
    embs, pad, att = model.embed_prefix(images, img_masks, tokens, masks)
    att_2d = modeling_pi05.make_att_2d_masks(pad, att)
    positions = torch.cumsum(pad, dim=1) - 1
    model.paligemma_with_expert.paligemma.model.language_model.config._attn_implementation = "eager"  # noqa: SLF001
    _, cache = model.paligemma_with_expert.forward(
        attention_mask=modeling_pi05.prepare_attention_masks_4d(att_2d),
        position_ids=positions,
        past_key_values=None,
        inputs_embeds=[embs, None],
        use_cache=True,
    )
    dt = torch.tensor(-1.0 / num_steps, dtype=torch.float32)
    time = torch.tensor(1.0, dtype=torch.float32)
    x = noise.clone()
    times = []
    while time >= -dt / 2:
        times.append(float(time))
        v = model.denoise_step(pad, cache, x, time.expand(x.shape[0]))
        x += dt * v
        time += dt
    return x, times


def denormalize(actions: np.ndarray, stats: dict, action_dim: int) -> np.ndarray:
    """DenormalizeLiberoAction._denormalize: float32 actions times float64 statistics."""
    a = actions[..., :action_dim]
    mask = np.array(stats["mask"]) if "mask" in stats else np.ones_like(stats["mean"], dtype=bool)
    return np.where(mask, a * np.array(stats["std"]) + np.array(stats["mean"]), a)


def libero_gripper(action: np.ndarray) -> np.ndarray:
    """normalize_gripper_action(binarize=True) then invert_gripper_action, on the last value."""
    a = action.copy()
    a[..., -1] = np.sign(2 * (a[..., -1] - 0.0) / (1.0 - 0.0) - 1)
    a[..., -1] = a[..., -1] * -1.0
    return a


# ----------------------------------------------------------------------------------------------
# Cases


def run_case(name: str, spec: dict, out_root: Path) -> Path:
    case_dir = out_root / name
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    fam = pi_oracle.FAMILIES["pi05"]
    gen = np.random.default_rng(spec["seed"])
    src_ckpt = REPO_ROOT / "tests" / "fixtures" / spec["source"] / "checkpoint"
    _cfg, policy, pre, _post = pi_oracle.load_checkpoint(fam, src_ckpt, spec["tiny"])
    policy.float()
    model = policy.model
    ckpt = case_dir / "checkpoint"
    run = write_run_dir(spec, ckpt, policy, gen)
    B, R = 2, spec["resolution"]
    cams = [key for key, _ in spec["cameras"]]
    images, files = write_images(case_dir, [(k, (R, R), fmt) for k, fmt in spec["cameras"]], B, spec["seed"])

    stats = run["stats"]
    state = gen.normal(np.array(stats["proprio"]["mean"]), np.array(stats["proprio"]["std"]), (B, STATE_DIM)).astype(np.float32)
    max_action_dim = spec["max_action_dim"]
    noise = torch.from_numpy(gen.standard_normal((B, spec["chunk"], max_action_dim)).astype(np.float32))

    # Inputs as FluxVLA's evaluation builds them, one item at a time, stacked.
    pixels = {
        key: torch.from_numpy(
            np.stack([transform_image(images[key][b], spec["means"][i], spec["stds"][i], R) for b in range(B)])
        ).float()
        for i, key in enumerate(cams)
    }
    tok = FluxTokenizer(ckpt / "tokenizer" / "tokenizer.model")
    rows = [tok.padded(t, spec["max_len"]) for t in spec["instructions"]]
    tokens = torch.tensor([r[0] for r in rows], dtype=torch.int64)
    masks = torch.tensor([r[1] for r in rows], dtype=torch.bool)
    p = stats["proprio"]
    norm_state = ((state.astype(np.float64) - np.array(p["mean"])) / (np.array(p["std"]) + 1e-6)).astype(np.float32)

    probes = pi_oracle.Probes(fam, policy, pre)
    saved_sinusoid = modeling_pi05.create_sinusoidal_pos_embedding
    modeling_pi05.create_sinusoidal_pos_embedding = sinusoid_f32
    try:
        with torch.no_grad():
            img_masks = [torch.ones(B, dtype=torch.bool) for _ in cams]
            x, times = predict_action(model, [pixels[k] for k in cams], img_masks, tokens, masks, noise, spec["steps"])
    finally:
        modeling_pi05.create_sinusoidal_pos_embedding = saved_sinusoid
    assert len(times) == spec["steps"], times
    actions_norm = x[..., :ACTION_DIM].numpy()
    actions = np.stack([denormalize(actions_norm[b], stats["action"], ACTION_DIM) for b in range(B)])
    libero = np.stack([libero_gripper(actions[b]) for b in range(B)])

    n_layers = len(model.paligemma_with_expert.paligemma.model.language_model.layers)
    t: dict[str, torch.Tensor] = {
        "input.state": torch.from_numpy(state),
        "input.noise": noise,
        "pre.lang_tokens": tokens,
        "pre.lang_mask": masks.to(torch.uint8),
        "pre.state": torch.from_numpy(norm_state),
        "out.actions_normalized": torch.from_numpy(actions_norm).float(),
        "out.actions": torch.from_numpy(actions).float(),
        "out.actions_libero": torch.from_numpy(libero).float(),
        "mid.velocity.step0": probes.velocities[0].float(),
        "mid.adarms_cond.step0": probes.adarms[0].float(),
    }
    for key, vis in zip(cams, probes.vision_out, strict=True):
        t[f"input.image.{key}"] = torch.from_numpy(images[key])
        t[f"pre.pixels.{key}"] = pixels[key]
        t[f"mid.vision.{key}"] = vis.float()
    embs, pad_masks, _ = probes.prefix
    t["mid.prefix_embs"] = embs.float()
    t["mid.prefix_pad_mask"] = pad_masks.to(torch.uint8)
    for layer in (0, n_layers - 1):
        k, v = probes.kv[layer]
        t[f"mid.prefix_k.{layer}"] = k.float()
        t[f"mid.prefix_v.{layer}"] = v.float()
    t = {k: v.contiguous() for k, v in t.items()}
    weights = sorted((ckpt / "checkpoints").iterdir())[-1].name
    meta = {
        "versions": json.dumps(versions()),
        "family": "pi05_fluxvla",
        "fluxvla": FLUXVLA,
        "restates": json.dumps(RESTATES),
        "source_checkpoint": spec["source"] + "/checkpoint",
        "weights_file": "checkpoints/" + weights,
        "case": spec["desc"],
        "instructions": json.dumps(spec["instructions"]),
        "prompts": json.dumps([s.strip().replace("_", " ").replace("\n", " ") for s in spec["instructions"]]),
        "cameras": json.dumps(cams),
        "input_files": json.dumps(files),
        "times": json.dumps(times),
        "tokenizer": json.dumps(
            {
                "file": "checkpoint/tokenizer/tokenizer.model (the stand-in PaliGemma model of tests/fixtures/paligemma_hub)",
                "bos_id": tok.sp.bos_id(),
                "newline_ids": tok.sp.encode("\n"),
                "max_len": spec["max_len"],
                "pad_id": 0,
            }
        ),
        "network": "lerobot 0.6.1 PI05Pytorch (float32) on the source checkpoint's weights, tiny sizes as in "
        + spec["source"] + "'s metadata (replaced)",
        "generator": GENERATOR,
    }
    write_safetensors(case_dir / "oracle.safetensors", t, meta)
    return case_dir


# ----------------------------------------------------------------------------------------------
# Tokenizer cases


TOKENIZER_STRINGS = [
    LIBERO_TASK,
    "put the white mug on the left plate and put the yellow and white mug on the right plate",
    "turn on the stove and put the moka pot on it",
    "pick up the book and place it in the back compartment of the caddy",
    UNDERSCORE_TASK,
    "\t  pick up the red cube \u3000\n",
    "Pick up the blue block, then put it on the plate.",
    "push the button 10 times: then wait 5 seconds",
    "rotate the knob by 90\u00b0 counter-clockwise",
    "d\u00e9placer le cube rouge \u00e0 gauche",
    "\u628a\u7ea2\u8272\u65b9\u5757\u653e\u5728\u76d8\u5b50\u4e0a",
    "grab the \U0001F34E and the \U0001F955",
    "two  spaces   and\ttabs",
    "___",
    "",
    "a" * 300,
    " ".join(["stack the green cube on top of the yellow one"] * 8),
    "Task: pick up the cube, State: 12 127;\nAction: ",
    "say <eos> then <bos>",
    "<pad><unk>",
]


def cmd_tokenizer(args) -> None:
    tok = FluxTokenizer(TOKENIZER_MODEL)
    special = {"<bos>", "<eos>", "<pad>", "<unk>"}
    cases = []
    for s in TOKENIZER_STRINGS:
        ids = tok.ids(s)
        cases.append({"text": s, "ids": ids, "ids_max_len_180": tok.padded(s, 180)[0][: min(len(ids), 180)],
                      "writes_special": any(w in s for w in special)})
    out = Path(args.out or FIXTURES / "tokenizer_cases.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "what": "FluxVLA's prompt ids: PaligemmaTokenizer.tokenize (libsentencepiece " + sentencepiece.__version__
        + ") on the stand-in PaliGemma tokenizer.model, and the first 180 (LiberoPromptFromInputs' cut)",
        "restates": RESTATES["prompt"],
        "fluxvla": FLUXVLA,
        "tokenizer_model": "tests/fixtures/paligemma_hub/.../tokenizer.model",
        "bos_id": tok.sp.bos_id(),
        "generator": "tools/oracle/fluxvla_oracle.py tokenizer",
        "cases": cases,
    }
    out.write_text(json.dumps(doc, ensure_ascii=False, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {out} ({len(cases)} strings)")


def cmd_fixtures(args) -> None:
    out = Path(args.out or FIXTURES)
    out.mkdir(parents=True, exist_ok=True)
    pi_oracle.ensure_tokenizer()
    names = args.cases.split(",") if args.cases else list(CASES)
    for name in names:
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
        print(f"wrote {run_case(name, CASES[name], out)}")


def main(argv: list[str] | None = None) -> None:
    import argparse

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fixtures")
    f.add_argument("--out", default="")
    f.add_argument("--cases", default="")
    t = sub.add_parser("tokenizer")
    t.add_argument("--out", default="")
    args = p.parse_args(argv)
    {"fixtures": cmd_fixtures, "tokenizer": cmd_tokenizer}[args.cmd](args)


if __name__ == "__main__":
    main(sys.argv[1:])
