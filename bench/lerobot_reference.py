"""Latency of an upstream lerobot policy (SmolVLA, pi0, pi0.5) on CPU (fp32), the reference the C++ engine is compared to.

Run inside the oracle venv:
  tools/oracle/run.sh bench/lerobot_reference.py --checkpoint DIR --image camera1=img.png ... \
      --state 0,0,0,0,0,0 --instruction "pick up the red cube" [--noise noise.safetensors] \
      [--warmup 2] [--iterations 10] [--out actions.safetensors]

The timed region is pre-processor + predict_action_chunk + post-processor for one observation (the full
action chunk); image decoding happens before it. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="lerobot checkpoint directory (upstream layout)")
    p.add_argument("--image", action="append", default=[], metavar="CAMERA=FILE",
                   help="camera key (full 'observation.images.x' or short 'x') and image file; repeat per camera")
    p.add_argument("--state", required=True, help="comma-separated state vector in robot units")
    p.add_argument("--instruction", required=True)
    p.add_argument("--noise", help="safetensors file with tensor 'noise' [1 or none, chunk, max_action_dim]")
    p.add_argument("--seed", type=int, default=0, help="noise seed when --noise is not given")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--threads", type=int, default=0, help="torch threads (default: number of cores)")
    p.add_argument("--out", help="write the last action chunk here as tensor 'actions' [1, chunk, action_dim]")
    p.add_argument("--embodiment-tag", default="", help="GR00T checkpoints: the embodiment (default: the only one)")
    return p.parse_args(argv)


def groot_setup(ckpt: Path, raw: dict, images: dict, state, args):
    """GR00T N1.7 in its raw NVIDIA layout: lerobot's GrootPolicy (GR00TN17 in float32, no autocast) with the N1.7
    processors; the backbone repository `model_name` names is read from the hub cache. The sampler's noise is drawn
    inside upstream (torch.randn in get_action_with_features), so it is handed in by replacing torch.randn there."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.groot.configuration_groot import GrootConfig
    from lerobot.policies.groot.modeling_groot import GrootPolicy
    from lerobot.policies.groot.processor_groot import GrootN17VLMEncodeStep
    from safetensors.torch import load_file

    kwargs = json.loads((ckpt / "processor_config.json").read_text())["processor_kwargs"]
    modalities = kwargs["modality_configs"]
    tag = args.embodiment_tag or (next(iter(modalities)) if len(modalities) == 1 else None)
    if tag not in modalities:
        raise SystemExit(f"--embodiment-tag: one of {sorted(modalities)}")
    stats = json.loads((ckpt / "statistics.json").read_text())[tag]
    dim = lambda kind: sum(len(stats[kind][k]["min"]) for k in modalities[tag][kind]["modality_keys"])
    cams = modalities[tag]["video"]["modality_keys"]
    images = {k.removeprefix("observation.images."): v for k, v in images.items()}
    if sorted(images) != sorted(cams):
        raise SystemExit(f"GR00T embodiment {tag} needs --image for {cams}")
    feats = {f"observation.images.{c}": PolicyFeature(type=FeatureType.VISUAL, shape=tuple(images[c].shape[1:]))
             for c in cams}
    feats["observation.state"] = PolicyFeature(type=FeatureType.STATE, shape=(dim("state"),))
    horizon = int(raw.get("action_horizon", 40))
    cfg = GrootConfig(base_model_path=str(ckpt), embodiment_tag=tag, input_features=feats,
                      output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(dim("action"),))},
                      max_state_dim=int(raw.get("max_state_dim", 132)), max_action_dim=int(raw.get("max_action_dim", 132)),
                      chunk_size=horizon, n_action_steps=horizon, use_bf16=False, device="cpu", push_to_hub=False)
    with contextlib.redirect_stdout(io.StringIO()):
        policy = GrootPolicy.from_pretrained(str(ckpt), config=cfg)
    policy = policy.to(torch.float32).eval()
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(ckpt))
    for s in pre.steps:
        if isinstance(s, GrootN17VLMEncodeStep):
            s.model_name = raw.get("model_name", s.model_name)  # lerobot's step names the Cosmos repository itself
    shape = (1, horizon, cfg.max_action_dim)
    if args.noise:
        noise = load_file(args.noise)["noise"].to(torch.float32).reshape(shape)
    else:
        noise = torch.randn(shape, generator=torch.Generator().manual_seed(args.seed), dtype=torch.float32)
    head = policy._groot_model.action_head
    real_method, real_randn = head.get_action_with_features, torch.randn

    def with_noise(*a, **k):
        torch.randn = lambda *ra, **rk: noise.clone()
        try:
            return real_method(*a, **k)
        finally:
            torch.randn = real_randn

    head.get_action_with_features = with_noise

    def step():
        batch = {f"observation.images.{c}": images[c].mul(255).round().to(torch.uint8) for c in cams}
        batch["observation.state"] = state.clone()
        batch["task"] = args.instruction
        with torch.no_grad():
            return post(policy.predict_action_chunk(pre(batch)))

    return cfg, step, noise


def main(argv=None) -> int:
    args = parse_args(argv)
    threads = args.threads or os.cpu_count() or 1
    torch.set_num_threads(threads)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

    import lerobot
    import transformers
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    from safetensors.torch import load_file, save_file

    ckpt = Path(args.checkpoint).resolve()
    images = {}
    for spec in args.image:
        if "=" not in spec:
            raise SystemExit(f"--image expects CAMERA=FILE, got {spec!r}")
        cam, file = spec.split("=", 1)
        key = cam if cam.startswith("observation.images.") else f"observation.images.{cam}"
        with Image.open(file) as im:
            arr = np.asarray(im.convert("RGB"), dtype=np.uint8)
        images[key] = torch.from_numpy(arr.copy()).permute(2, 0, 1).to(torch.float32).div(255.0)[None]
    state = torch.tensor([[float(v) for v in args.state.split(",")]], dtype=torch.float32)

    t0 = time.perf_counter()
    old_cwd = os.getcwd()
    os.chdir(ckpt)  # a relative vlm_model_name resolves against the checkpoint
    raw = json.loads((ckpt / "config.json").read_text())
    try:
        if "type" not in raw and raw.get("model_type") == "Gr00tN1d7":
            cfg, step, noise = groot_setup(ckpt, raw, images, state, args)
            load_s = time.perf_counter() - t0
        else:
            cfg = PreTrainedConfig.from_pretrained(str(ckpt))
            cfg.device = "cpu"
            policy_class = get_policy_class(cfg.type)
            with contextlib.redirect_stdout(io.StringIO()):
                policy = policy_class.from_pretrained(str(ckpt), config=cfg)
            policy = policy.to(torch.float32).eval()
            pre, post = make_pre_post_processors(cfg, pretrained_path=str(ckpt))
            load_s = time.perf_counter() - t0

            missing = [k for k in cfg.image_features if k not in images]
            if missing:
                raise SystemExit(f"missing --image for camera(s): {', '.join(missing)}")
            unknown = [k for k in images if k not in cfg.image_features]
            if unknown:
                raise SystemExit(f"checkpoint has no camera(s) {', '.join(unknown)}; it expects {list(cfg.image_features)}")
            if state.shape[1] != cfg.robot_state_feature.shape[0]:
                raise SystemExit(f"--state has {state.shape[1]} values, checkpoint expects {cfg.robot_state_feature.shape[0]}")

            if args.noise:
                noise = load_file(args.noise)["noise"].to(torch.float32)
                if noise.ndim == 2:
                    noise = noise[None]
            else:
                gen = torch.Generator().manual_seed(args.seed)
                noise = torch.randn((1, cfg.chunk_size, cfg.max_action_dim), generator=gen, dtype=torch.float32)
            want = (1, cfg.chunk_size, cfg.max_action_dim)
            if tuple(noise.shape) != want:
                raise SystemExit(f"noise has shape {tuple(noise.shape)}, checkpoint needs {want}")

            def step():
                batch = dict(images)
                batch["observation.state"] = state.clone()
                batch["task"] = args.instruction
                with torch.no_grad():
                    processed = pre(batch)
                    actions = policy.predict_action_chunk(processed, noise=noise.clone())
                    return post(actions)

        for _ in range(args.warmup):
            step()
        times = []
        actions = None
        for _ in range(args.iterations):
            t = time.perf_counter()
            actions = step()
            times.append((time.perf_counter() - t) * 1000.0)
    finally:
        os.chdir(old_cwd)

    if args.out and actions is not None:
        save_file({"actions": actions.to(torch.float32).contiguous()}, args.out)
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    result = {
        "engine": "lerobot-pytorch",
        "policy": getattr(cfg, "type", "groot"),
        "checkpoint": str(ckpt),
        "device": "cpu",
        "dtype": "float32",
        "threads": threads,
        "warmup": args.warmup,
        "iterations": args.iterations,
        "median_ms": statistics.median(times) if times else None,
        "mean_ms": statistics.fmean(times) if times else None,
        "min_ms": min(times) if times else None,
        "max_ms": max(times) if times else None,
        "load_s": load_s,
        "peak_rss_mb": rss_kb / 1024.0,
        "chunk_shape": list(actions.shape) if actions is not None else None,
        "versions": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "transformers": transformers.__version__,
            "lerobot": getattr(lerobot, "__version__", "unknown"),
        },
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
