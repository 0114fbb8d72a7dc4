"""Relative-action oracle for GR00T N1.7: lerobot's native decode of a checkpoint trained with
`use_relative_action` (GrootN17ActionDecodeStep: relative groups unnormalised with `relative_action` min/max, per
chunk step when the statistics are 2-D, then made absolute against the raw state the pack step cached -- NON_EEF
groups add the state group, EEF groups in XYZ_ROT6D compose poses with relative_eef_to_absolute).

The weights are the committed tiny checkpoint of tests/fixtures/gr00t_n17/cam2_new (embodiment row 1), unchanged; the
sidecars are written anew for one embodiment `relative_arm`:
  state  eef (9: xyz + the first two rows of a rotation), joints (4), gripper (1)
  action eef (9) RELATIVE EEF XYZ_ROT6D on state eef, per-step relative_action statistics [6][9];
         joints (4) RELATIVE NON_EEF on state joints, one row of statistics;
         gripper (1) ABSOLUTE (q01/q99 of `action`, as use_percentiles says)
  use_relative_action true, 6 valid steps of the model's 8-row horizon.
The camera PNGs are cam2_new's. The state's eef group is a real pose (a rotation about a tilted axis), so the
composed poses are rotations too. The model runs as gr00t_oracle.py runs it (GrootPolicy.from_pretrained, fp32, no
autocast, stand-in hub cache, the noise injected in place of torch.randn), through lerobot's own pre- and
post-processors.

Writes tests/fixtures/gr00t_n17_relative/ (checkpoint/, inputs/, oracle.safetensors).
Usage: tools/oracle/run.sh gr00t_relative_oracle.py [--out DIR]
"""

from __future__ import annotations

import os
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[2]
os.environ["HF_HUB_CACHE"] = str(os.environ.get("TETHER_GR00T_HUB", _ROOT / "tests" / "fixtures" / "gr00t_hub"))

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import shutil  # noqa: E402

import gr00t_oracle as go  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from smolvla_oracle import write_safetensors  # noqa: E402

SOURCE = "cam2_new"
TAG = "relative_arm"
ROW = 1
HORIZON = go.VALID_HORIZON  # 6 valid steps
INSTRUCTION = "Slide the drawer shut, then lift the cup."
NOISE_SEED = 31000
STATS_SEED = 59

EMBODIMENT = dict(
    index=ROW,
    video=["front", "wrist"],
    state=[("eef", 9), ("joints", 4), ("gripper", 1)],
    action=[("eef", 9), ("joints", 4), ("gripper", 1)],
    action_types=["EEF", "NON_EEF", "NON_EEF"],
    enum_case="upper",
    language="annotation.human.task_description",
    degenerate={},
    horizon=HORIZON,
    seed=STATS_SEED,
)

IDENTITY_ROT6D = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def relative_statistics(horizon: int) -> dict:
    """relative_action statistics of an eef (xyz + rot6d, per step) and a joints (4, one row) group: small
    translations growing with the step, rotations near the identity."""
    lo, hi = [], []
    for step in range(horizon):
        t = 0.02 * (step + 1)
        lo.append([round(v, 6) for v in [-t, -t, -t] + list(IDENTITY_ROT6D - 0.15 - 0.01 * step)])
        hi.append([round(v, 6) for v in [t, 1.5 * t, t] + list(IDENTITY_ROT6D + 0.15 + 0.01 * step)])
    return {"eef": with_moments(lo, hi),
            "joints": with_moments([-0.3, -0.2, -0.25, -0.1], [0.3, 0.25, 0.2, 0.15])}


def statistics() -> dict:
    gen = np.random.default_rng(STATS_SEED)
    stats = {"state": {}, "action": {}, "relative_action": {}}
    for modality in ("state", "action"):
        for key, dim in EMBODIMENT[modality]:
            stats[modality][key] = go.group_stats(gen, dim, None)
    stats["relative_action"] = relative_statistics(HORIZON)
    return stats


def with_moments(lo, hi) -> dict:
    """min/max plus the other statistics Isaac-GR00T writes (lerobot's stats flattening reads mean and std too;
    only min/max decode a relative group)."""
    a, b = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    r = lambda x: np.round(x, 6).tolist()  # noqa: E731
    return {"min": r(a), "max": r(b), "mean": r((a + b) / 2), "std": r((b - a) / 4), "q01": r(a + (b - a) * 0.02),
            "q99": r(b - (b - a) * 0.02)}


def modality_config() -> dict:
    return {
        "video": {"delta_indices": [0], "modality_keys": EMBODIMENT["video"]},
        "state": {"delta_indices": [0], "modality_keys": [k for k, _ in EMBODIMENT["state"]]},
        "action": {
            "delta_indices": list(range(HORIZON)),
            "modality_keys": [k for k, _ in EMBODIMENT["action"]],
            "action_configs": [
                {"rep": "RELATIVE", "type": "EEF", "format": "XYZ_ROT6D", "state_key": "eef"},
                {"rep": "RELATIVE", "type": "NON_EEF", "format": "DEFAULT", "state_key": "joints"},
                {"rep": "ABSOLUTE", "type": "NON_EEF", "format": "DEFAULT", "state_key": None},
            ],
        },
        "language": {"delta_indices": [0], "modality_keys": [EMBODIMENT["language"]]},
    }


def write_checkpoint(source_ckpt: Path, ckpt: Path) -> None:
    if ckpt.exists():
        shutil.rmtree(ckpt)
    ckpt.mkdir(parents=True)
    for f in source_ckpt.iterdir():
        if f.name.startswith("model") or f.name == "config.json":
            shutil.copy2(f, ckpt / f.name)
    pc = go.processor_config(go.TINY_IMAGE, {}, max_state_dim=16, max_action_dim=16, model_name=go.TINY_REPO,
                             horizon=go.MODEL_HORIZON)
    pc["processor_kwargs"]["modality_configs"] = {TAG: modality_config()}
    pc["processor_kwargs"]["use_relative_action"] = True
    (ckpt / "processor_config.json").write_text(go.dump_json(pc))
    (ckpt / "statistics.json").write_text(go.dump_json({TAG: statistics()}))
    (ckpt / "embodiment_id.json").write_text(go.dump_json({TAG: ROW}))


def raw_state() -> list[float]:
    rot = rotation(np.array([0.3, -0.5, 0.8]), 0.7)
    eef = [0.42, -0.13, 0.31] + list(rot[0]) + list(rot[1])
    return [round(float(v), 6) for v in eef] + [0.25, -0.6, 1.1, 0.05] + [0.4]


def main() -> None:
    torch.set_num_threads(1)
    logging.getLogger("lerobot").setLevel(logging.ERROR)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="")
    args = p.parse_args()
    out = Path(args.out or go.REPO_ROOT / "tests" / "fixtures" / "gr00t_n17_relative")
    out.mkdir(parents=True, exist_ok=True)
    go.ensure_tiny_hub()
    from lerobot.policies.groot.processor_groot import GrootN17ActionDecodeStep
    from lerobot.policies.groot.utils import relative_eef_to_absolute

    source = go.REPO_ROOT / "tests" / "fixtures" / "gr00t_n17" / SOURCE
    ckpt = out / "checkpoint"
    write_checkpoint(source / "checkpoint", ckpt)
    inputs = out / "inputs"
    inputs.mkdir(exist_ok=True)
    images = {}
    for cam in EMBODIMENT["video"]:
        shutil.copy2(source / "inputs" / f"{cam}.png", inputs / f"{cam}.png")
        images[cam] = go.decode_png(inputs / f"{cam}.png")

    go.EMBODIMENTS[TAG] = EMBODIMENT  # groot_config reads the state and action widths from it
    spec = {"tag": TAG, "cameras": [(c, images[c].shape[:2]) for c in EMBODIMENT["video"]]}
    cfg, policy, pre, post, load_info = go.load_policy(ckpt.resolve(), spec)
    decode = [s for s in post.steps if isinstance(s, GrootN17ActionDecodeStep)]
    assert len(decode) == 1 and decode[0].use_relative_action, "the decode step does not decode relative actions"

    state = torch.tensor([raw_state()], dtype=torch.float32)
    noise = torch.randn((1, go.MODEL_HORIZON, 16), generator=torch.Generator().manual_seed(NOISE_SEED))
    batch = {f"observation.images.{k}": torch.from_numpy(v).permute(2, 0, 1).unsqueeze(0).contiguous()
             for k, v in images.items()}
    batch["observation.state"] = state.clone()
    batch["task"] = INSTRUCTION
    log: list = []
    with torch.no_grad(), go.injected_noise(policy._groot_model.action_head, noise, log):
        processed = pre(batch)
        chunk = policy.predict_action_chunk(processed)
        actions = post(chunk)
    assert len(log) == 1, log

    # The same chunk decoded step by step here, to record the relative values before re-anchoring and to check the
    # decode step did what its source says.
    stats = statistics()
    y = chunk[0, :HORIZON].numpy()
    eef_rel = (np.clip(y[:, :9], -1, 1) + 1.0) * 0.5 * (np.float32(stats["relative_action"]["eef"]["max"]) -
                                                       np.float32(stats["relative_action"]["eef"]["min"])) + \
        np.float32(stats["relative_action"]["eef"]["min"])
    joints_rel = (np.clip(y[:, 9:13], -1, 1) + 1.0) * 0.5 * (np.float32(stats["relative_action"]["joints"]["max"]) -
                                                            np.float32(stats["relative_action"]["joints"]["min"])) + \
        np.float32(stats["relative_action"]["joints"]["min"])
    s = state[0].numpy()
    eef_abs = relative_eef_to_absolute(eef_rel[None].astype(np.float32), s[None, :9])[0]
    joints_abs = joints_rel.astype(np.float32) + s[9:13]
    got = actions[0].numpy()
    assert np.abs(got[:, :9] - eef_abs).max() < 1e-6 and np.abs(got[:, 9:13] - joints_abs).max() < 1e-6, (
        got, eef_abs, joints_abs)

    t = {
        "input.state": state,
        "input.noise": noise,
        "pre.state": processed["state"].float(),
        "out.actions_chunk": chunk.float().contiguous(),
        "out.relative.eef": torch.from_numpy(np.ascontiguousarray(eef_rel, dtype=np.float32)),
        "out.relative.joints": torch.from_numpy(np.ascontiguousarray(joints_rel, dtype=np.float32)),
        "out.actions": actions.float().contiguous(),
    }
    for k in EMBODIMENT["video"]:
        t[f"input.image.{k}"] = torch.from_numpy(images[k]).unsqueeze(0)
    meta = {
        "versions": json.dumps(go.versions()),
        "case": __doc__.split("\n\n")[1],
        "instruction": INSTRUCTION,
        "embodiment_tag": TAG,
        "camera_keys": json.dumps(EMBODIMENT["video"]),
        "input_files": json.dumps({k: f"inputs/{k}.png" for k in EMBODIMENT["video"]}),
        "action_groups": json.dumps(EMBODIMENT["action"]),
        "noise_injection": json.dumps({"how": "gr00t_oracle.injected_noise: torch.randn replaced during "
                                       "get_action_with_features", "calls": log,
                                       "noise": f"torch.randn((1, 8, 16), generator=manual_seed({NOISE_SEED}))"}),
        "run": json.dumps({"loader": "gr00t_oracle.load_policy (GrootPolicy.from_pretrained, fp32, no autocast)",
                           "processors": "make_pre_post_processors(config, pretrained_path=ckpt)",
                           "decode": "GrootN17ActionDecodeStep with use_relative_action from processor_config.json; "
                           "the raw state from GrootN17PackInputsStep.get_cached_raw_state",
                           "param_dtypes_after_load": load_info["param_dtypes"]}),
        "generator": "tools/oracle/run.sh gr00t_relative_oracle.py",
    }
    write_safetensors(out / "oracle.safetensors", t, meta)
    print(f"wrote {out}: actions {tuple(actions.shape)}, max |action| {float(actions.abs().max()):.3f}")


if __name__ == "__main__":
    main()
