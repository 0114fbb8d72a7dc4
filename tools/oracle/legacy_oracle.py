"""Legacy-layout oracle: a tiny SmolVLA checkpoint as lerobot wrote them before 0.4, and upstream's run on it
after upstream's own migration.

Before lerobot 0.4 a policy directory held only `config.json` and `model.safetensors`; the dataset statistics
lived inside the weights as the buffers of the policy's normalisation modules (`normalize_inputs.buffer_<key>.<stat>`,
`normalize_targets.buffer_<key>.<stat>`, `unnormalize_outputs.buffer_<key>.<stat>`, with the dots of the feature
key written as underscores) and there were no processor files. lerobot 0.6.1 cannot use such statistics until
`lerobot/processor/migrate_policy_normalization.py` has rewritten the directory.

This script
  1. builds a tiny policy with upstream code (the same shapes as the smolvla fixtures),
  2. writes it in the pre-0.4 layout to tests/fixtures/smolvla/<case>/checkpoint (config.json, model.safetensors
     with the statistics buffers, and the offline backbone folder vlm/ the fixtures share),
  3. runs upstream's migration script on that directory into a scratch directory,
  4. runs the upstream policy on the migrated checkpoint with fixed inputs and noise and records
     tests/fixtures/smolvla/<case>/oracle.safetensors exactly as smolvla_oracle.py does for its cases.

Tether loads the LEGACY directory; its parity test compares against the migrated upstream run.

Usage: tools/oracle/run.sh legacy_oracle.py [--out DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import torch
from lerobot.configs import NormalizationMode
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.processor import migrate_policy_normalization
from safetensors.torch import load_file

from smolvla_oracle import (
    INSTR_LONG,
    INSTR_SHORT,
    REPO_ROOT,
    TINY_BASE_VOCAB,
    TINY_TEXT,
    TINY_VISION,
    build_checkpoint,
    make_config,
    make_stats,
    record_oracle,
    train_tokenizer,
    working_dir,
    write_images,
    write_safetensors,
)

CASE = "legacy_pre04"
SPEC = dict(
    desc=(
        "pre-0.4 layout: config.json + model.safetensors with normalize_inputs / normalize_targets / "
        "unnormalize_outputs buffers, no processor files; 1 camera (96x128 PNG), state 6 MIN_MAX with one "
        "degenerate dimension, action 6 MEAN_STD with one zero std, chunk 8, 4 steps, fp32"
    ),
    seed=4000,
    weights_seed=44,
    cameras=[("observation.images.camera1", (96, 128), "png")],
    state_dim=6,
    action_dim=6,
    stats=True,
    norm="MIN_MAX/MEAN_STD",
    chunk_size=8,
    num_steps=4,
    num_expert_layers=-1,
    self_attn_every_n_layers=2,
    instructions=[INSTR_SHORT, INSTR_LONG],
)
# Which old normalisation module held which feature's buffers (as the pre-0.4 policies registered them).
MODULES = {
    "observation.state": ["normalize_inputs"],
    "action": ["normalize_targets", "unnormalize_outputs"],
}
STATS_FOR = {NormalizationMode.MEAN_STD: ("mean", "std"), NormalizationMode.MIN_MAX: ("min", "max")}


class _NoCard:
    def save(self, *_args, **_kwargs) -> None:
        pass


def write_legacy(upstream: Path, legacy: Path, cfg, stats: dict) -> list[str]:
    """The pre-0.4 directory: upstream's config.json and weights plus the statistics buffers; returns their names."""
    if legacy.exists():
        shutil.rmtree(legacy)
    legacy.mkdir(parents=True)
    shutil.copy(upstream / "config.json", legacy / "config.json")
    shutil.copytree(upstream / "vlm", legacy / "vlm")
    tensors = load_file(str(upstream / "model.safetensors"))
    buffers = []
    for key, modules in MODULES.items():
        feature_type = {**cfg.input_features, **cfg.output_features}[key].type
        mode = cfg.normalization_mapping[feature_type.value]
        for module in modules:
            for stat in STATS_FOR[mode]:
                name = f"{module}.buffer_{key.replace('.', '_')}.{stat}"
                tensors[name] = torch.from_numpy(np.asarray(stats[key][stat], np.float32).copy())
                buffers.append(name)
    write_safetensors(legacy / "model.safetensors", tensors, {"format": "pt"})
    return sorted(buffers)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO_ROOT / "tests" / "fixtures" / "smolvla"))
    args = p.parse_args()
    case_dir = Path(args.out) / CASE
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    B = 2
    spec = SPEC
    cfg = make_config(
        cameras=[(k, hw) for k, hw, _ in spec["cameras"]],
        state_dim=spec["state_dim"],
        action_dim=spec["action_dim"],
        norm="MEAN_STD",
        chunk_size=spec["chunk_size"],
        num_steps=spec["num_steps"],
        num_vlm_layers=TINY_TEXT["num_hidden_layers"],
        num_expert_layers=spec["num_expert_layers"],
        self_attn_every_n_layers=spec["self_attn_every_n_layers"],
        resize=(TINY_VISION["image_size"], TINY_VISION["image_size"]),
    )
    cfg.normalization_mapping = {
        "VISUAL": NormalizationMode.IDENTITY,
        "STATE": NormalizationMode.MIN_MAX,
        "ACTION": NormalizationMode.MEAN_STD,
    }
    stats = make_stats(cfg, np.random.default_rng(spec["weights_seed"] + 7), degenerate_dim=True)

    with tempfile.TemporaryDirectory(prefix="tether-legacy-") as tmp:
        tmp = Path(tmp)
        upstream = tmp / "upstream"
        build_checkpoint(
            upstream, cfg, seed=spec["weights_seed"], text=TINY_TEXT, vision=TINY_VISION, scale_factor=2,
            tok=train_tokenizer(TINY_BASE_VOCAB), stats=None, dtype=torch.float32,
        )
        legacy = case_dir / "checkpoint"
        buffers = write_legacy(upstream, legacy, cfg, stats)

        # Upstream's own migration script, run from the legacy directory (the policy config names its backbone by
        # the relative path "vlm"). Its last step renders a model card, which asks the hub to validate the card's
        # YAML; offline that fails, so the card (documentation only, written after every other file) is skipped.
        migrated = tmp / "migrated"
        argv = ["migrate_policy_normalization", "--pretrained-path", str(legacy), "--output-dir", str(migrated)]
        log = io.StringIO()
        with working_dir(legacy), mock.patch.object(sys, "argv", argv), \
                mock.patch.object(PreTrainedPolicy, "generate_model_card", lambda *a, **k: _NoCard()), \
                contextlib.redirect_stdout(log):
            migrate_policy_normalization.main()
        shutil.copytree(legacy / "vlm", migrated / "vlm")
        files = sorted(p.name for p in migrated.iterdir())
        assert "policy_preprocessor.json" in files and "policy_postprocessor.json" in files, files
        kept = load_file(str(migrated / "model.safetensors"))
        assert not any(b in kept for b in buffers), "the migration kept a statistics buffer"

        images, input_files = write_images(case_dir, spec["cameras"], B, spec["seed"])
        gen = np.random.default_rng(spec["seed"])
        st = stats["observation.state"]
        span = np.maximum(st["max"] - st["min"], 1.0)
        state = (st["min"][None, :] + gen.uniform(0.0, 1.0, (B, spec["state_dim"])).astype(np.float32) * span[None, :])
        state = state.astype(np.float32)
        state[:, -1] = st["min"][-1]  # the degenerate dim sits exactly on its single dataset value
        noise = torch.from_numpy(gen.standard_normal((B, cfg.chunk_size, cfg.max_action_dim)).astype(np.float32))

        record_oracle(
            case_dir, migrated, images, input_files, state, noise, spec,
            generator="tools/oracle/legacy_oracle.py",
            extra_meta={
                "stats": (
                    "in the legacy weights as buffers; upstream ran on the output of "
                    "lerobot.processor.migrate_policy_normalization (STATE MIN_MAX, ACTION MEAN_STD, VISUAL IDENTITY)"
                ),
                "legacy_buffers": json.dumps(buffers),
                "migrated_files": json.dumps(files),
            },
        )
    print(f"wrote {case_dir}")


if __name__ == "__main__":
    torch.set_num_threads(max(1, os.cpu_count() or 1))  # as smolvla_oracle.py: torch's multi-thread resize kernel
    sys.exit(main())
