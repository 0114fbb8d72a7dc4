"""Real-time chunking oracle: upstream lerobot SmolVLA with its RTCProcessor on a committed tiny checkpoint.

Reads tests/fixtures/smolvla/cam1_stats (checkpoint, input images, state, instructions) without changing it, runs
upstream once without RTC for a previous chunk, then with RTC (other noise) towards that chunk's leftover, for
several (inference delay, execution horizon, schedule, max guidance weight) settings. Writes
tests/fixtures/smolvla_rtc/oracle.safetensors.

Usage: tools/oracle/run.sh rtc_oracle.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import safetensors
import torch
from lerobot.configs import RTCAttentionSchedule
from lerobot.policies.rtc.configuration_rtc import RTCConfig

from smolvla_oracle import REPO_ROOT, decode_image, load_checkpoint, to_model_image, versions, working_dir, write_safetensors

SOURCE_CASE = REPO_ROOT / "tests" / "fixtures" / "smolvla" / "cam1_stats"
EXECUTED = 2  # actions of the previous chunk already run; the rest is the leftover
CASES = [  # name, inference_delay, execution_horizon, schedule, max_guidance_weight
    ("linear_d2_h5", 2, 5, RTCAttentionSchedule.LINEAR, 10.0),
    ("exp_d3_h8", 3, 8, RTCAttentionSchedule.EXP, 5.0),  # horizon past the leftover: capped upstream
    ("ones_d4_h2", 4, 2, RTCAttentionSchedule.ONES, 10.0),  # delay past the horizon
    ("zeros_d1_h4", 1, 4, RTCAttentionSchedule.ZEROS, 2.5),
]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO_ROOT / "tests" / "fixtures" / "smolvla_rtc"))
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    ckpt = SOURCE_CASE / "checkpoint"
    src = safetensors.safe_open(str(SOURCE_CASE / "oracle.safetensors"), "pt")
    meta = src.metadata()
    cameras = json.loads(meta["cameras"])
    files = json.loads(meta["input_files"])
    instructions = json.loads(meta["instructions"])
    state = src.get_tensor("input.state")
    B = state.shape[0]

    cfg, policy, pre, post = load_checkpoint(ckpt)
    images = {k: np.stack([decode_image(SOURCE_CASE / "inputs" / f) for f in files[k]]) for k in cameras}
    batch = {k: to_model_image(a) for k, a in images.items()}
    batch["observation.state"] = state.clone()
    batch["task"] = list(instructions)
    gen = torch.Generator().manual_seed(20260)
    shape = (B, cfg.chunk_size, cfg.max_action_dim)
    prev_noise = torch.randn(shape, generator=gen)
    noise = torch.randn(shape, generator=gen)

    t: dict[str, torch.Tensor] = {"input.prev_noise": prev_noise, "input.noise": noise}
    with working_dir(ckpt), torch.no_grad():
        processed = pre(batch)
        prev_norm = policy.predict_action_chunk(processed, noise=prev_noise.clone())
        leftover_norm = prev_norm[:, EXECUTED:, :].contiguous()
        t["input.prev_actions"] = post(leftover_norm.clone()).float()  # robot units, as a client holds them
        t["input.prev_actions_normalized"] = leftover_norm.float()
        plain = policy.predict_action_chunk(processed, noise=noise.clone())
        t["out.no_rtc.actions_normalized"] = plain.float()
        for name, delay, horizon, schedule, max_w in CASES:
            policy.config.rtc_config = RTCConfig(
                prefix_attention_schedule=schedule, max_guidance_weight=max_w, execution_horizon=horizon
            )
            policy.init_rtc_processor()
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
        "source_case": "tests/fixtures/smolvla/cam1_stats (checkpoint and inputs)",
        "executed": str(EXECUTED),
        "cases": json.dumps(
            [
                {"name": n, "inference_delay": d, "execution_horizon": h, "schedule": s.value.lower(), "max_guidance_weight": w}
                for n, d, h, s, w in CASES
            ]
        ),
        "generator": "tools/oracle/rtc_oracle.py",
    }
    write_safetensors(out / "oracle.safetensors", t, info)
    print(f"wrote {out / 'oracle.safetensors'}")


if __name__ == "__main__":
    main()
