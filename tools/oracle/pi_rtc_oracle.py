"""Real-time chunking oracle for pi0 / pi0.5: upstream lerobot's RTCProcessor on a committed tiny checkpoint.

Reads one case of tests/fixtures/pi0 or tests/fixtures/pi05 (cam2_bf16 of each) without changing
it (checkpoint, input images, state, instructions), loads it with the same replaced sizes as pi_oracle.py, runs
upstream once without RTC for a previous chunk, then with RTC enabled (RTCConfig on the policy config,
init_rtc_processor, other noise) towards that chunk's leftover through predict_action_chunk's
inference_delay / prev_chunk_left_over / execution_horizon, for several (delay, horizon, schedule, max guidance
weight) settings. Writes tests/fixtures/<family>_rtc/oracle.safetensors.

With --relative it reads the use_relative_actions case (cam1_relative) and follows lerobot's rollout
(lerobot/rollout/inference/rtc.py): the previous chunk is made absolute against the state of its own observation
and its leftover kept in robot units; the robot then moves (a new state, input.state), and the leftover is made
relative to the new state and normalised by reanchor_relative_rtc_prefix before it steers the sampler. Writes
tests/fixtures/<family>_rtc_relative/oracle.safetensors.

Usage: tools/oracle/run.sh pi_rtc_oracle.py --family pi0|pi05 [--relative] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pi_oracle  # noqa: I001  (sets HF_HUB_CACHE before any Hugging Face import)
import numpy as np
import safetensors
import torch
from lerobot.configs import RTCAttentionSchedule
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.policies.rtc.relative import reanchor_relative_rtc_prefix
from lerobot.processor import NormalizerProcessorStep, RelativeActionsProcessorStep

from pi_oracle import CASES, FAMILIES, REPO_ROOT, load_checkpoint, make_batch
from smolvla_oracle import decode_image, versions, write_safetensors

# Cases whose action statistics have no degenerate dimension: a client sends the leftover in robot units, and a
# dimension whose std is 0 (or q01 == q99) cannot be mapped back to the normalised value upstream guides towards.
SOURCE = {"pi0": "cam2_bf16", "pi05": "cam2_bf16"}
RELATIVE_SOURCE = {"pi0": "cam1_relative", "pi05": "cam1_relative"}
MOVED = 1.75  # --relative: how far every joint moved (robot units) between the two chunks' observations
EXECUTED = 2  # actions of the previous chunk already run; the rest is the leftover
SETTINGS = [  # name, inference_delay, execution_horizon, schedule, max_guidance_weight
    ("linear_d2_h5", 2, 5, RTCAttentionSchedule.LINEAR, 10.0),
    ("exp_d3_h8", 3, 8, RTCAttentionSchedule.EXP, 5.0),  # horizon past the leftover: capped upstream
    ("ones_d4_h2", 4, 2, RTCAttentionSchedule.ONES, 10.0),  # delay past the horizon
    ("zeros_d1_h4", 1, 4, RTCAttentionSchedule.ZEROS, 2.5),
]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--family", choices=sorted(FAMILIES), required=True)
    p.add_argument("--relative", action="store_true", help="the use_relative_actions case, re-anchored as lerobot does")
    p.add_argument("--out", default="")
    args = p.parse_args()
    fam = FAMILIES[args.family]
    suffix = "_rtc_relative" if args.relative else "_rtc"
    out = Path(args.out or REPO_ROOT / "tests" / "fixtures" / f"{fam.name}{suffix}")
    out.mkdir(parents=True, exist_ok=True)
    case = (RELATIVE_SOURCE if args.relative else SOURCE)[fam.name]
    spec = CASES[fam.name][case]
    source = REPO_ROOT / "tests" / "fixtures" / fam.name / case
    ckpt = source / "checkpoint"

    src = safetensors.safe_open(str(source / "oracle.safetensors"), "pt")
    meta = src.metadata()
    cameras = [k for k in json.loads(meta["cameras"]) if k not in json.loads(meta["missing_cameras"])]
    files = json.loads(meta["input_files"])
    instructions = json.loads(meta["instructions"])
    state = src.get_tensor("input.state").numpy()
    B = state.shape[0]

    cfg, policy, pre, post = load_checkpoint(fam, ckpt, spec["tiny"])
    images = {k: np.stack([decode_image(source / "inputs" / f) for f in files[k]]) for k in cameras}
    gen = torch.Generator().manual_seed(20260)
    shape = (B, cfg.chunk_size, cfg.max_action_dim)
    prev_noise = torch.randn(shape, generator=gen)
    noise = torch.randn(shape, generator=gen)

    t: dict[str, torch.Tensor] = {"input.prev_noise": prev_noise, "input.noise": noise}
    with torch.no_grad():
        processed = pre(make_batch(images, state, instructions))
        prev_norm = policy.predict_action_chunk(processed, noise=prev_noise.clone())
        leftover_norm = prev_norm[:, EXECUTED:, :].contiguous()
        t["input.prev_actions"] = post(leftover_norm.clone()).float()  # robot units, as a client holds them
        t["input.prev_actions_normalized"] = leftover_norm.float()
        if args.relative:
            # The next observation: the robot moved. Its preprocessing keeps the new state, and the leftover, absolute
            # against the old one, is re-anchored on it as lerobot's rollout does.
            state = (state + np.float32(MOVED)).astype(np.float32)
            t["input.state"] = torch.from_numpy(state)
            processed = pre(make_batch(images, state, instructions))
            relative = next(s for s in pre.steps if isinstance(s, RelativeActionsProcessorStep))
            normalizer = next(s for s in pre.steps if isinstance(s, NormalizerProcessorStep))
            leftover_norm = reanchor_relative_rtc_prefix(
                t["input.prev_actions"].clone(), torch.from_numpy(state), relative, normalizer, "cpu"
            ).contiguous()
            t["input.prev_actions_normalized"] = leftover_norm.float()
        plain = policy.predict_action_chunk(processed, noise=noise.clone())
        t["out.no_rtc.actions_normalized"] = plain.float()
        for name, delay, horizon, schedule, max_w in SETTINGS:
            policy.config.rtc_config = RTCConfig(
                enabled=True, prefix_attention_schedule=schedule, max_guidance_weight=max_w, execution_horizon=horizon
            )
            policy.init_rtc_processor()
            assert policy.model.rtc_processor is policy.rtc_processor and policy.model._rtc_enabled()
            guided = policy.predict_action_chunk(
                processed,
                noise=noise.clone(),
                inference_delay=delay,
                prev_chunk_left_over=leftover_norm.clone(),
                execution_horizon=horizon,
            )
            t[f"out.{name}.actions_normalized"] = guided.float()
            t[f"out.{name}.actions"] = post(guided.clone()).float()
    t = {k: v.contiguous() for k, v in t.items()}
    info = {
        "versions": json.dumps(versions()),
        "family": fam.name,
        "source_case": f"tests/fixtures/{fam.name}/{case} (checkpoint and inputs)",
        "executed": str(EXECUTED),
        "cases": json.dumps(
            [
                {"name": n, "inference_delay": d, "execution_horizon": h, "schedule": s.value.lower(), "max_guidance_weight": w}
                for n, d, h, s, w in SETTINGS
            ]
        ),
        "replaced": meta["replaced"],
        "generator": f"tools/oracle/pi_rtc_oracle.py --family {fam.name}" + (" --relative" if args.relative else ""),
    }
    write_safetensors(out / "oracle.safetensors", t, info)
    print(f"wrote {out / 'oracle.safetensors'}")


if __name__ == "__main__":
    main()
