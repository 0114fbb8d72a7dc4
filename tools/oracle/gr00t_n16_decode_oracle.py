"""Action-decoding oracle for GR00T N1.6: the two decodes of Isaac-GR00T's StateActionProcessor.unapply_action that
the other N1.6 fixtures do not reach, each on its own embodiment of one checkpoint.

  relative_arm   use_relative_action: a RELATIVE group is unnormalised with its `relative_action` min/max (per chunk
                 step when the statistics are 2-D, never the percentiles), then made absolute against the last raw
                 state of its `state_key` group: NON_EEF adds it, EEF in XYZ_ROT6D composes homogeneous poses
                 T_state @ T_relative, each rotation from the first two rows by Gram-Schmidt and held as a scipy
                 Rotation, as pose.EndEffectorPose does.
  mean_std_arm   action groups listed in the action modality's mean_std_embedding_keys (as Isaac-GR00T's own
                 oxe_widowx and oxe_google configs list x, y, z, roll, pitch, yaw): x * std + mean, unclipped, and x
                 itself where std is 0; the other groups min/max.

Isaac-GR00T is not on PyPI, so the decode is restated from its source (files and commit in the metadata); the EEF
composition is also checked against lerobot's relative_eef_to_absolute (ran), and scripts/check_isaac_gr00t.sh runs
Isaac-GR00T's own StateActionProcessor on both cases when given an Isaac-GR00T checkout.

The weights are the committed tiny N1.6 checkpoint of tests/fixtures/gr00t_n16 (rebuilt from their seed and checked
equal); the sidecars are written anew for the two embodiments (use_percentiles false, N1.6's default):
  relative_arm (projector row 10), the cameras of cam2_new_embodiment:
    state  eef (9: xyz + the first two rows of a rotation), joints (4), gripper (1), all min/max
    action eef (9) RELATIVE EEF XYZ_ROT6D on state eef, per-step relative_action statistics [6][9];
           joints (4) RELATIVE NON_EEF on state joints, one row of statistics; gripper (1) ABSOLUTE
  mean_std_arm (projector row 2), the camera of cam1_libero_panda:
    state  eef_pos (3), eef_rot (3), pad (1), gripper (1), all min/max
    action xyz (3) and rpy (3, one dimension with std 0) mean/std; gripper (1) min/max
  6 valid steps of the model's 8-row horizon. The state's eef group is a real pose (a rotation about a tilted axis),
so the composed poses are rotations too. The model runs as gr00t_n16_oracle.py runs its cases.

Writes tests/fixtures/gr00t_n16_decode/ (checkpoint/, cases/relative_arm/, cases/mean_std_arm/).
Usage: tools/oracle/run.sh gr00t_n16_decode_oracle.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
from pathlib import Path

import gr00t_n16_oracle as g16
import gr00t_relative_oracle as n17_relative  # the N1.7 relative fixture's statistics and pose helpers
import numpy as np
import torch
from scipy.spatial.transform import Rotation

HORIZON = 6
ISAAC_DECODE = "NVIDIA/Isaac-GR00T@5a6167f09c85b0e2e2702964d62cc0ef0b6fba3b"
ABSOLUTE = {"rep": "ABSOLUTE", "type": "NON_EEF", "format": "DEFAULT", "state_key": None}


def relative_state() -> dict[str, np.ndarray]:
    rot = n17_relative.rotation(np.array([0.3, -0.5, 0.8]), 0.7)
    eef = [0.42, -0.13, 0.31] + list(rot[0]) + list(rot[1])
    return {"eef": eef, "joints": [0.25, -0.6, 1.1, 0.05], "gripper": [0.4]}


EMBODIMENTS = {
    "relative_arm": dict(
        row=g16.N16_EMBODIMENT_IDS["new_embodiment"], source_case="cam2_new_embodiment",
        instruction="Slide the drawer shut, then lift the cup.",
        video=["front", "wrist"],
        state=[("eef", 9), ("joints", 4), ("gripper", 1)], sin_cos=[], mean_std=[],
        action=[("eef", 9), ("joints", 4), ("gripper", 1)], action_types=["EEF", "NON_EEF", "NON_EEF"],
        action_configs=[{"rep": "RELATIVE", "type": "EEF", "format": "XYZ_ROT6D", "state_key": "eef"},
                        {"rep": "RELATIVE", "type": "NON_EEF", "format": "DEFAULT", "state_key": "joints"},
                        ABSOLUTE],
        action_mean_std=[],
        language="annotation.human.task_description", horizon=HORIZON, degenerate={}, seed=71,
        raw_state=relative_state,
    ),
    "mean_std_arm": dict(
        row=g16.N16_EMBODIMENT_IDS["libero_panda"], source_case="cam1_libero_panda",
        instruction="Put the spoon on the towel.",
        video=["image"],
        state=[("eef_pos", 3), ("eef_rot", 3), ("pad", 1), ("gripper", 1)], sin_cos=[], mean_std=[],
        action=[("xyz", 3), ("rpy", 3), ("gripper", 1)], action_types=["NON_EEF", "NON_EEF", "NON_EEF"],
        action_configs=[ABSOLUTE, ABSOLUTE, ABSOLUTE],
        action_mean_std=["xyz", "rpy"],
        language="annotation.human.action.task_description", horizon=HORIZON,
        degenerate={"action": ("rpy", 1)}, seed=73,
        raw_state=lambda: {"eef_pos": [0.31, -0.02, 0.12], "eef_rot": [0.1, -1.2, 2.9], "pad": [0.0],
                           "gripper": [0.7]},
    ),
}


def statistics(tag: str) -> dict:
    emb = EMBODIMENTS[tag]
    stats = g16.embodiment_statistics(emb)
    if any(c["rep"] == "RELATIVE" for c in emb["action_configs"]):
        stats["relative_action"] = n17_relative.relative_statistics(HORIZON)
    return stats


def raw_state(tag: str) -> dict[str, np.ndarray]:
    groups = EMBODIMENTS[tag]["raw_state"]()
    return {k: np.round(np.asarray(v, np.float64), 6).astype(np.float32)[None, :] for k, v in groups.items()}


def eef_pose(v: np.ndarray) -> np.ndarray:
    """pose.EndEffectorPose(translation=v[:3], rotation=v[3:], rotation_type="rot6d").homogeneous."""
    r = np.asarray(v[3:9], np.float64).reshape(2, 3)
    row1 = r[0] / np.linalg.norm(r[0])
    row2 = r[1] - np.dot(row1, r[1]) * row1
    row2 = row2 / np.linalg.norm(row2)
    m = np.vstack([row1, row2, np.cross(row1, row2)])
    t = np.eye(4)
    t[:3, :3] = Rotation.from_matrix(m).as_matrix()
    t[:3, 3] = v[:3]
    return t


def decode_actions(tag: str, action_pred: np.ndarray, state: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """Gr00tN1d6Processor.decode_action + StateActionProcessor.unapply_action (use_relative_action true): rows
    [0, horizon), columns per group; a mean_std_embedding_keys group as x * std + mean where std != 0 (x elsewhere),
    stored in the input's float32; a RELATIVE group with relative_action min/max, the others with action min/max,
    (clip(n, -1, 1) + 1) / 2 * (max - min) + min in float64; then the RELATIVE ones made absolute against
    state[state_key][-1]. Returns the absolute groups and the relative values before re-anchoring."""
    emb = EMBODIMENTS[tag]
    stats = statistics(tag)
    out, relative, start = {}, {}, 0
    for (key, dim), cfg in zip(emb["action"], emb["action_configs"], strict=True):
        n = action_pred[..., :HORIZON, start:start + dim]
        is_relative = cfg["rep"] == "RELATIVE"
        st = {k: np.array(v) for k, v in stats["relative_action" if is_relative else "action"][key].items()}
        if key in emb["action_mean_std"]:
            values = np.zeros_like(n)
            m = st["std"] != 0
            values[..., m] = n[..., m] * st["std"][m] + st["mean"][m]
            values[..., ~m] = n[..., ~m]
        else:
            values = (np.clip(n, -1.0, 1.0) + 1.0) / 2.0 * (st["max"] - st["min"]) + st["min"]
        if is_relative:
            relative[key] = values
            ref = state[cfg["state_key"] or key][-1]
            if cfg["type"] == "NON_EEF":
                values = ref + values
            else:
                t_ref = eef_pose(ref)
                rows = []
                for row in values.reshape(-1, dim):
                    t = t_ref @ eef_pose(row)
                    rot = Rotation.from_matrix(t[:3, :3]).as_matrix()
                    rows.append(np.concatenate([t[:3, 3], rot[:2, :].reshape(-1)]))
                values = np.stack(rows).reshape(values.shape)
        out[key] = values
        start += dim
    return out, relative


def write_checkpoint(committed: Path, ckpt: Path) -> None:
    ckpt.mkdir(parents=True)
    for f in (committed / "checkpoint").iterdir():
        if f.name.startswith("model") or f.name == "config.json":
            shutil.copy2(f, ckpt / f.name)
    pc = g16.processor_config(EMBODIMENTS)
    for tag, emb in EMBODIMENTS.items():
        action = pc["processor_kwargs"]["modality_configs"][tag]["action"]
        action["action_configs"] = emb["action_configs"]
        action["mean_std_embedding_keys"] = emb["action_mean_std"] or None
    pc["processor_kwargs"]["use_relative_action"] = True
    (ckpt / "processor_config.json").write_text(json.dumps(pc, indent=2) + "\n")
    (ckpt / "statistics.json").write_text(json.dumps({t: statistics(t) for t in EMBODIMENTS}, indent=2) + "\n")
    rows = {t: e["row"] for t, e in EMBODIMENTS.items()}
    (ckpt / "embodiment_id.json").write_text(json.dumps(rows, indent=2) + "\n")


def run(model, tok, ids, tag: str, out: Path, relative_eef_to_absolute) -> None:
    emb = EMBODIMENTS[tag]
    source = g16.CASES[emb["source_case"]]
    spec = dict(source, tag=tag, instruction=emb["instruction"],
                desc=f"{tag} (row {emb['row']}), the cameras of {emb['source_case']}; action configs "
                     f"{json.dumps(emb['action_configs'])}, mean/std action groups {emb['action_mean_std']}")
    state = raw_state(tag)
    recorded: dict = {}

    def decode(tag_, action_pred):
        absolute, relative = decode_actions(tag_, action_pred[0], state)
        recorded.update(relative)
        if "eef" in relative:  # lerobot's EEF composition (ran): Isaac-GR00T's scipy round trip aside, equal
            lerobot_eef = relative_eef_to_absolute(relative["eef"][None].astype(np.float32), state["eef"])[0]
            err = float(np.abs(lerobot_eef - absolute["eef"]).max())
            if err > 1e-6:
                raise RuntimeError(f"the restated EEF composition differs from lerobot's by {err}")
        return {k: v[None] for k, v in absolute.items()}

    g16.decode_actions = decode
    g16.raw_state = lambda tag_, seed: state
    with torch.no_grad():
        g16.run_case(model, tok, ids, tag, spec, out)
    case = out / "cases" / tag
    from safetensors import safe_open

    with safe_open(str(case / "oracle.safetensors"), "pt") as f:
        tensors = {k: f.get_tensor(k).clone() for k in f.keys()}  # copies: the file is rewritten below
        meta = f.metadata()
    for key, values in recorded.items():
        tensors[f"out.relative.{key}"] = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))
    meta["action_decode"] = json.dumps({
        "restated": [f"{ISAAC_DECODE}:gr00t/data/state_action/{f}" for f in
                     ("state_action_processor.py", "pose.py", "action_chunking.py")] +
                    [f"{ISAAC_DECODE}:gr00t/data/utils.py"],
        "action_configs": emb["action_configs"],
        "action_mean_std_embedding_keys": emb["action_mean_std"],
        "checked": "the EEF composition against lerobot.policies.groot.utils.relative_eef_to_absolute (ran), 1e-6",
    })
    meta["generator"] = "tools/oracle/run.sh gr00t_n16_decode_oracle.py"
    g16.write(case, tensors, meta)
    actions = tensors["out.actions"]
    print(f"wrote {case}: actions {tuple(actions.shape)}, max |action| {float(actions.abs().max()):.3f}")


def main() -> None:
    torch.set_num_threads(1)
    logging.getLogger("lerobot").setLevel(logging.ERROR)
    logging.getLogger("transformers").setLevel(logging.ERROR)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(g16.REPO_ROOT / "tests" / "fixtures" / "gr00t_n16_decode"))
    args = p.parse_args()
    out = Path(args.out)
    committed = g16.REPO_ROOT / "tests" / "fixtures" / "gr00t_n16"
    for sub in ("checkpoint", "cases"):
        if (out / sub).exists():
            shutil.rmtree(out / sub)
    from lerobot.policies.groot.utils import relative_eef_to_absolute
    from safetensors.torch import load_file
    from transformers import AutoTokenizer

    with tempfile.TemporaryDirectory() as tmp:
        # The committed weights, rebuilt from their seed: equal tensor for tensor.
        model, _ = g16.build_checkpoint(Path(tmp) / "checkpoint")
        index = json.loads((committed / "checkpoint" / "model.safetensors.index.json").read_text())
        for shard in sorted(set(index["weight_map"].values())):
            for name, v in load_file(str(committed / "checkpoint" / shard)).items():
                if not torch.equal(v.float(), model.state_dict()[name]):
                    raise RuntimeError(f"{name} differs from the committed checkpoint")
    tok = AutoTokenizer.from_pretrained(str(committed / "eagle"))
    tok.padding_side = "left"
    ids = {t: tok.convert_tokens_to_ids(t) for t in ("<IMG_CONTEXT>", "<img>", "</img>")}

    write_checkpoint(committed, out / "checkpoint")
    g16.EMBODIMENTS = EMBODIMENTS  # the case runner reads the embodiment's groups and statistics from here
    g16.N16_EMBODIMENT_IDS = {t: e["row"] for t, e in EMBODIMENTS.items()}
    for tag in EMBODIMENTS:
        run(model, tok, ids, tag, out, relative_eef_to_absolute)


if __name__ == "__main__":
    sys.exit(main())
